"""The application layer: the ``tensormass`` command line, off-screen rendering, the progress
bar and the live viewer in the browser. It calls every layer below; nothing below calls it."""
