"""The application layer: the ``tensormass`` command line, off-screen rendering and the progress
bar. It calls every layer below; nothing below calls it."""
