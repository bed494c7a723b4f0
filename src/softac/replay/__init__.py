"""Replay: the buffers (ring, flat, frames, HER), the collector that fills them, the exploration noise."""
