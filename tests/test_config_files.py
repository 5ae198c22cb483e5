"""`--config` takes a named config, a .py file with get_config(), or a run's own config.json (re-running a run from
it is what users do); anything else, a syntax error or a retyped field is one line naming the file."""
import dataclasses
import json
import subprocess
import sys

import pytest

from sc3_jax.core.config import load_config
from sc3_jax.core.errors import UserError


def test_a_runs_own_config_json_reads_back_as_the_config_it_was_written_from(tmp_path):
    cfg = load_config("tiny")
    (tmp_path / "config.json").write_text(json.dumps(dataclasses.asdict(cfg)))
    assert load_config(str(tmp_path / "config.json")) == cfg


@pytest.mark.parametrize("name, text, words", [
    ("c.yaml", "model: {}", "a .py file with get_config()"),
    ("c.py", "def get_config(arg=None)\n    return 1\n", "c.py:1"),
    ("c.py", "x = 1\n", "defines no get_config"),
    ("c.py", "def get_config(arg=None):\n    return 1\n", "must return"),
    ("config.json", '{"model": {"dim": -192, "depth": "four"}}', "model.depth"),
    ("config.json", '[1, 2]', "JSON object"),
])
def test_a_config_file_that_is_not_one_is_a_line_naming_the_file(tmp_path, name, text, words):
    (tmp_path / name).write_text(text)
    with pytest.raises(UserError, match=words) as e:
        load_config(str(tmp_path / name))
    assert "\n" not in str(e.value) and name in str(e.value)


def test_sc3_train_with_a_yaml_config_ends_in_one_line_not_a_traceback(tmp_path):
    (tmp_path / "c.yaml").write_text("model: {}")
    r = subprocess.run([sys.executable, "-m", "sc3_jax.cli", "train", "--config", str(tmp_path / "c.yaml")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode in (1, 2) and "Traceback" not in r.stderr
    assert "c.yaml" in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr

