"""warpgnn: a real-time digital twin of the human liver (see DESIGN.md)."""

__version__ = "0.1.0"
