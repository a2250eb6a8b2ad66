"""The ``kbs`` command: thin commands over the library (parse, call, print)."""
