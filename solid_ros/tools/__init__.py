"""Offline tools: bag replay, the demo, evaluation metrics, plots, progress display."""
