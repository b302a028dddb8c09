"""The CRCs an MCAP file carries: checked before a replay trusts it, written into our own bags.

MCAP protects its contents with CRC-32s: one per chunk (of the uncompressed records), one over
the whole data section (in the DataEnd record) and one over the summary (in the Footer); a
writer may leave any of them 0, meaning "not computed". :func:`verify_mcap` checks every one
that is present, reading the file with the ``mcap`` package, and refuses a damaged file with a
:class:`~solid_ros.core.errors.BagError` that says where the damage is: a replay stops with one
line instead of decoding changed bytes as points. rosbags writes MCAP files without CRCs;
:func:`seal_crcs` fills them in after writing, so every bag this package writes can be checked.
"""

from __future__ import annotations

import os
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from solid_ros.core.errors import BagError

__all__ = ['McapCheck', 'seal_crcs', 'verify_mcap']

MAGIC = b'\x89MCAP0\r\n'
_CHUNK, _DATA_END, _FOOTER = 0x06, 0x0F, 0x02
_RECORD = struct.Struct('<BQ')  # opcode, content length
_FOOTER_SIZE = _RECORD.size + 8 + 8 + 4  # summary_start, summary_offset_start, summary_crc


@dataclass(frozen=True)
class McapCheck:
    """What :func:`verify_mcap` checked.

    Attributes:
        chunks: chunks in the file.
        chunks_checked: chunks that carry a CRC (all of them verified).
        data_section_checked: the data-section CRC was present and verified.
        summary_checked: the summary CRC was present and verified.
    """

    chunks: int
    chunks_checked: int
    data_section_checked: bool
    summary_checked: bool

    @property
    def has_crcs(self) -> bool:
        """Whether any CRC was present (damage can only be detected where one is)."""
        return bool(self.chunks_checked or self.data_section_checked or self.summary_checked)

    def describe(self) -> str:
        """One phrase for summaries and reports."""
        if not self.has_crcs:
            return 'no CRCs in the file: damage cannot be detected'
        parts = [f'{self.chunks_checked} of {self.chunks} chunk CRCs']
        if self.data_section_checked:
            parts.append('data section CRC')
        if self.summary_checked:
            parts.append('summary CRC')
        return 'verified ' + ', '.join(parts)


def _decompress(compression: str, data: bytes, size: int) -> bytes:
    if compression == '':
        return data
    if compression == 'zstd':
        import zstandard

        out: bytes = zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
        return out
    if compression == 'lz4':
        import lz4.frame  # type: ignore[import-untyped]

        lz4_out: bytes = lz4.frame.decompress(data)
        return lz4_out
    raise BagError(f'unsupported MCAP chunk compression {compression!r}')


def verify_mcap(path: str | Path) -> McapCheck:
    """Check every CRC an MCAP file carries and its record structure.

    Raises:
        BagError: one line naming the file and the damage (a chunk, the data section or the
            summary fails its CRC, or a record is malformed).
    """
    from mcap.records import Chunk, DataEnd, Footer
    from mcap.stream_reader import CRCValidationError, StreamReader

    p = Path(path)
    chunks = checked = 0
    data_checked = False
    footer: Any = None
    try:
        size = os.path.getsize(p)
        with p.open('rb') as f:
            reader = StreamReader(f, emit_chunks=True, validate_crcs=True,
                                  record_size_limit=size)
            for record in reader.records:
                if isinstance(record, Chunk):
                    chunks += 1
                    if record.uncompressed_crc == 0:
                        continue
                    raw = _decompress(record.compression, record.data,
                                      record.uncompressed_size)
                    if zlib.crc32(raw) != record.uncompressed_crc:
                        raise BagError(
                            f'{p}: MCAP chunk {chunks} (log times '
                            f'{record.message_start_time / 1e9:.3f} to '
                            f'{record.message_end_time / 1e9:.3f} s) fails its CRC check: the '
                            'bag is damaged and its messages cannot be trusted')
                    checked += 1
                elif isinstance(record, DataEnd):
                    data_checked = record.data_section_crc != 0  # the reader verified it
                elif isinstance(record, Footer):
                    footer = record
            summary_checked = _check_summary(f, p, footer, size)
    except BagError:
        raise
    except CRCValidationError as err:
        raise BagError(f'{p}: MCAP data section fails its CRC check ({chunks} chunks verified '
                       "or without CRC): the bag is damaged outside the messages' chunks, in "
                       'records that say how to read them') from err
    except Exception as err:  # the mcap reader raises many types for malformed records
        text = ' '.join(str(err).split())[:160] or type(err).__name__
        raise BagError(f'{p}: damaged or truncated MCAP file: {type(err).__name__}: '
                       f'{text}') from err
    return McapCheck(chunks, checked, data_checked, summary_checked)


def _check_summary(f: IO[bytes], p: Path, footer: Any, size: int) -> bool:
    if footer is None or footer.summary_crc == 0 or footer.summary_start == 0:
        return False
    end = size - len(MAGIC) - 4  # up to and including the footer's summary_offset_start
    if not 0 < footer.summary_start < end:
        raise BagError(f'{p}: damaged MCAP file: summary offset {footer.summary_start} lies '
                       'outside the file')
    f.seek(footer.summary_start)
    crc = zlib.crc32(f.read(end - footer.summary_start))
    if crc != footer.summary_crc:
        raise BagError(f'{p}: MCAP summary fails its CRC check: the index of the bag is damaged')
    return True


def seal_crcs(path: str | Path) -> None:
    """Fill in the chunk, data-section and summary CRCs an MCAP writer left 0, in place.

    Raises:
        BagError: the file is not an MCAP file this function understands.
    """
    p = Path(path)
    with p.open('r+b') as f:
        if f.read(len(MAGIC)) != MAGIC:
            raise BagError(f'{p}: not an MCAP file')
        data_crc = zlib.crc32(MAGIC)
        while True:
            start = f.tell()
            head = f.read(_RECORD.size)
            if len(head) < _RECORD.size:
                raise BagError(f'{p}: MCAP file ends before its DataEnd record')
            opcode, length = _RECORD.unpack(head)
            if opcode == _DATA_END:
                f.seek(start + _RECORD.size)
                if struct.unpack('<I', f.read(4))[0] == 0:
                    f.seek(start + _RECORD.size)
                    f.write(struct.pack('<I', data_crc))
                break
            content = bytearray(f.read(length))
            if opcode == _CHUNK:
                content = _seal_chunk(content)
                f.seek(start + _RECORD.size)
                f.write(content)
            data_crc = zlib.crc32(head + content, data_crc)
        _seal_summary(f, p)


def _seal_chunk(content: bytearray) -> bytearray:
    usize, crc = struct.unpack_from('<QI', content, 16)
    if crc:
        return content
    (clen,) = struct.unpack_from('<I', content, 28)
    compression = bytes(content[32:32 + clen]).decode()
    (dlen,) = struct.unpack_from('<Q', content, 32 + clen)
    data = bytes(content[40 + clen:40 + clen + dlen])
    struct.pack_into('<I', content, 24, zlib.crc32(_decompress(compression, data, usize)))
    return content


def _seal_summary(f: IO[bytes], p: Path) -> None:
    size = f.seek(0, os.SEEK_END)
    footer_at = size - len(MAGIC) - _FOOTER_SIZE
    f.seek(footer_at)
    opcode, _, summary_start, _, crc = struct.unpack('<BQQQI', f.read(_FOOTER_SIZE))
    if opcode != _FOOTER:
        raise BagError(f'{p}: MCAP footer not found')
    if summary_start == 0 or crc != 0:
        return
    f.seek(summary_start)
    value = zlib.crc32(f.read(size - len(MAGIC) - 4 - summary_start))
    f.seek(size - len(MAGIC) - 4)
    f.write(struct.pack('<I', value))
