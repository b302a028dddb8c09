"""A DDS participant of its own for a node's large messages (the back end's map and path).

On Fast DDS's default transport a message over its 512 KB shared-memory segment overruns the
*sending* participant's segment and loses what that participant sent just before it: with
the map going out of solid_node's own participant, ``/tf`` and ``~/odometry`` samples were
lost (best effort) or held up to 0.3-0.4 s until the writer repaired them (reliable; see the
doc/node.md, Transport of large clouds, and ``test/bench/bench_map_transport.py``). Sent from a
second participant (a second rclpy context), the large messages fill only its segment.

Its publishers take the owner node's resolved names (``~/map`` remapped as the owner's would
be), so launch files and remappings see the same topics. It needs no executor: a publisher
has no callbacks, and the middleware serves latched samples to late subscribers itself.
"""

from __future__ import annotations

from typing import Any

import rclpy
from rclpy.context import Context
from rclpy.node import Node
from rclpy.qos import QoSProfile

__all__ = ['BulkParticipant']


class BulkParticipant:
    """A second participant beside ``owner``, for publishers of large messages.

    Args:
        owner: the node whose names (namespace, remappings) the topics take; the participant
            joins its ROS domain, as node ``<owner name>_bulk`` in its namespace.
    """

    def __init__(self, owner: Node) -> None:
        self._owner = owner
        self._context = Context()
        # No arguments: the owner resolves the names (its remappings and namespace apply once).
        rclpy.init(args=[], context=self._context, domain_id=owner.context.get_domain_id())
        try:
            self._node = Node(f'{owner.get_name()}_bulk', namespace=owner.get_namespace(),
                              context=self._context, use_global_arguments=False,
                              enable_rosout=False, start_parameter_services=False)
        except BaseException:
            self._context.try_shutdown()
            raise
        self._closed = False

    def create_publisher(self, kind: Any, topic: str, qos: QoSProfile | int) -> Any:
        """A publisher on ``topic`` as the owner resolves it (``~/map`` -> its name)."""
        return self._node.create_publisher(kind, self._owner.resolve_topic_name(topic), qos)

    def close(self) -> None:
        """Destroy its node and shut its context down (idempotent)."""
        if not self._closed:
            self._closed = True
            self._node.destroy_node()
            self._context.try_shutdown()
