"""The bussing benchmark's own ``sc3`` commands: each module here, ``CMD.py``, is ``sc3 CMD`` (underscores as hyphens),
with the contract of ``sc3_jax/commands/`` (``SUMMARY``, ``Args`` or ``SUBCOMMANDS``, ``main(argv)``). ``sc3_jax/cli.py``
finds them on disk, so the core names none; they sit on the commands' floor (tests/test_imports.py)."""
