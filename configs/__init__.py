"""Named experiment configs, one file each, each defining ``get_config(arg=None)`` (``sc3 configs`` lists them).
Loaded by path with ``config.load_config(NAME)``, not imported as modules."""
