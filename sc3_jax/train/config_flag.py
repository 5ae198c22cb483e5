"""How a config field is spelt on the command line (``config_flag``): the one spelling of the fix that the planner's,
the shape check's and the memory plan's messages name."""
from __future__ import annotations

OWN_OPTION = {"data.path": "--data", "data.batch_size": "--batch"}  # config field -> its option in sc3 train / plan


def config_flag(key: str, value) -> str:
    """The command-line option that sets config field ``key`` ("section.field") to ``value``, as every command
    spells config overrides (``commands.parse_with_config``): ``--model.attention-impl ring``; the two fields with an
    option of their own in sc3 train and sc3 plan by it (``commands/flags.py`` CONFIG_FIELDS, a test ties the two):
    ``--batch 64``."""
    if key in OWN_OPTION:
        return f"{OWN_OPTION[key]} {value}"
    section, _, field = key.partition(".")
    name = field.replace("_", "-")
    if isinstance(value, bool):
        return f"--{section}.{'' if value else 'no-'}{name}"
    if isinstance(value, (tuple, list)):
        value = " ".join(map(str, value))
    return f"--{section}.{name} {value}"
