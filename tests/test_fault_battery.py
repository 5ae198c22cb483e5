"""The fault battery: every file kind sc3 reads (episode arrays, dataset.json, results records, a labels CSV, a world
model's config / params / orbax checkpoint, a LeRobot info.json) truncated, corrupted or retyped, and numeric options
drawn at their edges, each given to the real command (``sc3_jax.cli.main``, in this process) that reads it. For
every drawn fault: a non-zero exit, exactly one line on stderr, no traceback, the inputs unchanged and nothing
written outside OUT. The faults are drawn by ``hypothesis`` (a failure prints the example that breaks, and the
planted-fault test shows the battery catching a validator switched off)."""
import contextlib
import io
import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sc3_jax.cli import main
from sc3_jax.data.action_space import ActionSpace
from sc3_jax.data.episodes import Episode, EpisodeStore
from test_atomic import snapshot

DOCS = Path(__file__).parent.parent / "docs"
EXAMPLES = int(os.environ.get("BATTERY_EXAMPLES", 10))  # per test and file kind; BATTERY_EXAMPLES=200 digs deeper
BATTERY = settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
                   suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


def score(view):
    """The sweep's scorer, by name (``test_fault_battery:score``); never reached (the labels fail first)."""
    return {"success": True}


# -- the pristine inputs, built once -------------------------------------------------------------------------------
def _store(root: Path) -> Path:
    store = EpisodeStore(root, views=["cam"], fps=10, image_size=(8, 8), create=True,
                         action_space=ActionSpace("absolute", 2), has_pose=False)
    for i in range(2):
        store.write(Episode(f"e{i}", {"cam": np.full((6, 8, 8, 3), 30 * i, np.uint8)},
                            np.linspace(0, 1, 12, dtype=np.float32).reshape(6, 2), None, "pick it up"))
    return root


def _lerobot(root: Path) -> Path:
    from sc3_jax.data.lerobot_write import RawEpisode, write_lerobot

    eps = [RawEpisode({"observation.images.cam": np.full((3, 8, 8, 3), 40 * i, np.uint8)},
                      np.zeros((3, 2), np.float32), "t", np.zeros((3, 2), np.float32)) for i in range(2)]
    write_lerobot(root, eps, 10)
    return root


def _world_model(root: Path) -> Path:
    from test_sweep import tiny_world_model

    from sc3_jax import checkpoint

    wm = tiny_world_model(root)
    cfg, _, params = checkpoint.load(wm)
    conv = checkpoint.save_converted(root / "converted", cfg, params)
    shutil.copy(wm / "norm_stats.json", conv / "norm_stats.json")
    return wm


@pytest.fixture(scope="module")
def pristine(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("pristine")
    _store(root / "store")
    _lerobot(root / "lerobot")
    _world_model(root)
    results = root / "results"
    shutil.copytree(DOCS / "stores" / "cmd1_s1", results)
    import gzip
    (results / "results.jsonl").write_bytes(gzip.decompress((results / "results.jsonl.gz").read_bytes()))
    (results / "results.jsonl.gz").unlink()
    (root / "real.csv").write_text("policy,episode,success\nzero,e0,1\nzero,e1,0\n")
    return root


# -- one attack: copy the inputs, damage one file, run the command, check what it did -------------------------------
def attack(pristine: Path, damage, argv) -> str:
    """Run ``argv(root, out)`` on a copy of the inputs with ``damage(root)`` applied; assert the battery's promise
    and return the one line said."""
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "in"
        shutil.copytree(pristine, root)
        damage(root)
        out = Path(tmp) / "out"
        before = snapshot(Path(tmp))
        leaks = _ours_in_temp()
        err, said = io.StringIO(), io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(said):
            try:
                rc = main(argv(root, out))
            except SystemExit as e:  # a usage error from the option parser
                rc = e.code
            except BaseException as e:  # noqa: BLE001  (what a user would see as a traceback)
                raise AssertionError(f"traceback: {type(e).__name__}: {e}") from e
        lines = err.getvalue().strip().splitlines()
        assert rc not in (0, None), f"exit 0 for a fault; said {said.getvalue()[-500:]!r}"
        assert len(lines) == 1 and "Traceback" not in err.getvalue(), err.getvalue()[-3000:]
        after = {k: v for k, v in snapshot(Path(tmp)).items() if not k.startswith("out/")}
        assert after == before, f"changed outside OUT: {sorted(set(after.items()) ^ set(before.items()))[:3]}"
        assert _ours_in_temp() <= leaks, f"left in the system temp folder: {sorted(_ours_in_temp() - leaks)}"
        return lines[0]


def _ours_in_temp() -> set[str]:
    """The product's own names in the system temp folder (a failed `lerobot:` start once left sc3-lerobot-*.log
    there); other tests' temporaries (tmp*, pytest-*) come and go beside a parallel run, so only ours count."""
    return {p.name for p in Path(tempfile.gettempdir()).glob("sc3*")}


# -- the faults ---------------------------------------------------------------------------------------------------
WRONG = st.sampled_from(["abc", "", [], [1, 2], {}, {"a": 1}, None, True, -1, 0, 1e308, "nan"])


def truncate(rel: str, data):
    """Cut the file to a drawn length shorter than it is (a copy interrupted)."""
    def damage(root: Path):
        p = root / rel
        raw = p.read_bytes()
        p.write_bytes(raw[:data.draw(st.integers(0, len(raw) - 1), label=f"cut {rel}")])
    return damage


def corrupt_head(rel: str, data):
    """Overwrite the file's first bytes (magic, header) with drawn garbage."""
    def damage(root: Path):
        p = root / rel
        raw = p.read_bytes()
        junk = data.draw(st.binary(min_size=1, max_size=16).filter(lambda b: b != raw[:len(b)]), label="junk")
        p.write_bytes(junk + raw[len(junk):])
    return damage


def retype_npy(rel: str, data):
    """The array rewritten with a drawn wrong dtype or shape."""
    def damage(root: Path):
        p = root / rel
        x = np.load(p)
        how = data.draw(st.sampled_from(["str", "complex", "bool", "shape", "nan", "0d"]), label="retype")
        bad = {"str": lambda: x.astype(str), "complex": lambda: x.astype(np.complex64), "bool": lambda: x > 0,
               "shape": lambda: x.reshape(-1), "nan": lambda: np.full(x.shape, np.nan, np.float32),
               "0d": lambda: np.float32(1.0)}[how]()
        if how == "nan" and x.dtype == np.uint8:
            bad = x.astype(np.float32)  # frames as floats: wrong dtype
        np.save(p, bad)
    return damage


def retype_json(rel: str, keys: list[str], data, wrong=WRONG, optional=()):
    """One drawn field of a JSON object (``a.b`` nests) set to a drawn value of the wrong type, or removed where it
    must be there (not one of ``optional``)."""
    def damage(root: Path):
        p = root / rel
        obj = json.loads(p.read_text())
        key = data.draw(st.sampled_from(keys), label="field")
        *path, last = key.split(".")
        d = obj
        for k in path:
            d = d[k]
        # an optional field may be left out or null: those are not faults
        value = data.draw(wrong.filter(lambda v: v is not None) if key in optional
                          else st.one_of(wrong, st.just("<missing>")), label=f"{key} =")
        if value == "<missing>":
            d.pop(last, None)
        else:
            d[last] = value
        p.write_text(json.dumps(obj))
    return damage


# the commands that read each kind (OUT is theirs to write)
def export(root, out):
    return ["data", "export-lerobot", "--data", str(root / "store"), "--out", str(out / "lr")]


def report(root, out):
    return ["report", str(root / "results"), "--out", str(out / "report"), "--draws", "10"]


def rollout(root, out, model="wm"):
    return ["rollout", "--world-model", str(root / model), "--policy", "zero", "--data",
            str(root / "no_such_store"), "--out", str(out / "r"), "--no-video", "--no-progress"]


def sweep_real(root, out):
    return ["sweep", "episodes", "--data", str(root / "store"), "--world-model", str(root / "wm"),
            "--policies", "z=zero", "--scorer", "test_fault_battery:score", "--real", str(root / "real.csv"),
            "--out", str(out / "sweep"), "--no-progress"]


def import_lerobot(root, out):
    return ["data", "import-lerobot", "--data", str(root / "lerobot"), "--out", str(out / "store"), "--action-space",
            "absolute"]


EPISODE_FILES = ["store/e0/frames/cam.npy", "store/e1/actions.npy", "store/e0/actions.npy"]
HEADER_FIELDS = ["views", "fps", "action_dim", "image_size", "state", "ee_pose", "format"]
CONFIG_FIELDS = ["model.dim", "model.depth", "model.num_heads", "data.image_size", "data.views", "model",
                 "sample.steps", "model.rope_axes_dim", "data.fps", "data.state_dim"]
ROBOT_FACTS = ("data.fps", "data.state_dim")  # null or absent: read from the training store (a model saved before)
INFO_FIELDS = ["fps", "features", "data_path", "video_path", "codebase_version", "chunks_size"]


def episode_arrays(data):
    rel = data.draw(st.sampled_from(EPISODE_FILES), label="file")
    how = data.draw(st.sampled_from([truncate, corrupt_head, retype_npy]), label="fault")
    return how(rel, data), export


def dataset_json(data):
    how = data.draw(st.sampled_from(["truncate", "retype", "meta"]), label="fault")
    if how == "truncate":
        return truncate("store/dataset.json", data), export
    if how == "meta":  # an episode's meta.json, the store's other JSON
        prompt = retype_json("store/e1/meta.json", ["prompt"], data, st.sampled_from([[], {}, 3, None]), ["prompt"])
        return prompt, export
    return retype_json("store/dataset.json", HEADER_FIELDS, data, optional=["state"]), export


def results_records(data):
    i = data.draw(st.integers(0, 30), label="record")

    def damage(root: Path):
        p = root / "results" / "results.jsonl"
        lines = p.read_text().splitlines(keepends=True)
        r = json.loads(lines[i])
        how = data.draw(st.sampled_from(["outcome", "u", "policy", "mode", "cut", "missing", "garbage"]),
                        label="fault")
        if how == "outcome":
            r["objects"][0]["lifting"] = data.draw(st.sampled_from([2, "yes", [], None, 0.5]), label="outcome")
        elif how == "u":
            r["u"] = data.draw(st.sampled_from([[float("nan")], "low", [None], 3]), label="u") if "u" in r else [1]
        elif how == "policy":
            r["policy"] = data.draw(st.sampled_from(['x"><img src=x onerror=alert(1)>', "../x", 3, ""]),
                                    label="policy")
        elif how == "mode":
            r["mode"] = data.draw(st.sampled_from(["imagined", None, 1]), label="mode")
        elif how == "missing":
            r.pop("objects")
        if how == "cut":  # a complete line cut short (its newline kept): not a kill's cut line, a damaged one
            text = lines[i].rstrip("\n")
            lines[i] = text[:data.draw(st.integers(1, len(text) - 1), label="cut")] + "\n"
        elif how == "garbage":
            lines[i] = data.draw(st.sampled_from(["\x00\x01\n", "[1, 2]\n", "{\n", "NaN\n"]), label="line")
        else:
            lines[i] = json.dumps(r, allow_nan=True) + "\n"
        p.write_text("".join(lines))
    return damage, report


def labels_csv(data):
    how = data.draw(st.sampled_from(["truncate", "retype", "corrupt", "twice"]), label="fault")

    def damage(root: Path):
        p = root / "real.csv"
        text = p.read_text()
        if how == "truncate":  # inside the header line: a column lost
            p.write_text(text[:data.draw(st.integers(0, text.index("\n") - 1), label="cut")])
        elif how == "retype":
            p.write_text(text.replace("zero,e1,0", "zero,e1," + data.draw(
                st.sampled_from(["2", "maybe", "", "1.0", "[]", "nan"]), label="success")))
        elif how == "corrupt":
            at = data.draw(st.integers(0, len(text)), label="at")
            p.write_bytes(text.encode()[:at] + b"\xff\xfe\x00" + text.encode()[at:])
    if how == "twice":  # one file as a relative and an absolute path
        def argv(root, out):
            args = sweep_real(root, out)
            at = args.index("--real") + 2
            return [*args[:at], os.path.relpath(root / "real.csv"), *args[at:]]
        return (lambda root: None), argv
    return damage, sweep_real


def world_model_files(data):
    kind = data.draw(st.sampled_from(["config", "params", "checkpoint"]), label="file kind")
    if kind == "config":
        how = data.draw(st.sampled_from(["truncate", "retype"]), label="fault")
        if how == "truncate":
            return truncate("wm/config.json", data), rollout
        return retype_json("wm/config.json", CONFIG_FIELDS, data, optional=ROBOT_FACTS), rollout
    if kind == "params":
        how = data.draw(st.sampled_from(["truncate", "drop", "retype", "corrupt"]), label="fault")

        def damage(root: Path):
            p = root / "wm" / "params.npz"
            if how in ("truncate", "corrupt"):
                (truncate if how == "truncate" else corrupt_head)("wm/params.npz", data)(root)
                return
            with np.load(p) as z:
                arrays = {k: z[k] for k in z.files}
            name = data.draw(st.sampled_from(sorted(arrays)), label="array")
            if how == "drop":
                arrays.pop(name)
            else:
                arrays[name] = data.draw(st.sampled_from([arrays[name].astype(str), arrays[name].reshape(-1)[:1],
                                                          np.full(arrays[name].shape, np.inf, np.float32)]),
                                         label="as")
            np.savez(p, **arrays)
        return damage, rollout

    def damage(root: Path):  # the orbax checkpoint of a `sc3 convert` output: a data file cut short or lost
        files = sorted((p for p in (root / "converted" / "params").rglob("*") if p.is_file()),
                       key=lambda p: -p.stat().st_size)[:3]
        p = files[data.draw(st.integers(0, len(files) - 1), label="file")]
        if data.draw(st.booleans(), label="delete"):
            p.unlink()
        else:
            p.write_bytes(p.read_bytes()[:data.draw(st.integers(0, p.stat().st_size - 1), label="cut")])
    return damage, lambda root, out: rollout(root, out, "converted")


def lerobot_info(data):
    how = data.draw(st.sampled_from(["truncate", "retype", "template"]), label="fault")
    if how == "truncate":
        return truncate("lerobot/meta/info.json", data), import_lerobot
    if how == "retype":
        return retype_json("lerobot/meta/info.json", INFO_FIELDS, data, optional=["chunks_size"]), import_lerobot
    bad = st.sampled_from(["/etc/hostname", "../../x/{episode_index}.parquet", "data/{bogus}.parquet",
                           "data/{0}.parquet", "data/{chunk_index", "{chunk_index.x}"])
    key = data.draw(st.sampled_from(["data_path", "video_path"]), label="template")
    return retype_json("lerobot/meta/info.json", [key], data, bad), import_lerobot


KINDS = {"episode arrays": episode_arrays, "dataset.json": dataset_json, "results records": results_records,
         "labels CSV": labels_csv, "world model": world_model_files, "LeRobot info.json": lerobot_info}


@pytest.mark.parametrize("kind", list(KINDS))
@BATTERY
@given(data=st.data())
def test_every_damaged_file_kind_ends_in_one_line_and_changes_nothing_outside_out(pristine, kind, data):
    damage, argv = KINDS[kind](data)
    attack(pristine, damage, argv)


# -- options at their edges ---------------------------------------------------------------------------------------
INTS = st.sampled_from(["0", "-1", "200000000", "-99999"])  # values the parser takes, out of every int's range
FLOATS = st.sampled_from(["0", "-1", "1e9", "nan", "inf", "-inf", "1e308"])
SWEEP = {"--episodes": INTS, "--batch": INTS, "--calibration-episodes": st.just("-1"), "--episode-seconds": FLOATS}


def option_case(data):
    """(damage, argv) of a drawn option at a drawn edge, on otherwise whole inputs."""
    which = data.draw(st.sampled_from(["draws", "port", "episodes", "sweep", "horizon"]), label="option")
    if which == "draws":
        v = data.draw(INTS, label="draws")
        return ["report", "{root}/results", "--out", "{out}/r", "--draws", v]
    if which == "port":
        v = data.draw(st.sampled_from(["65536", "99999", "-1", "1000000000"]), label="port")
        return ["serve-policy", "--policy", "zero", "--port", v]
    if which == "episodes":
        v = data.draw(st.sampled_from(["5:9", "9", "1:0", "-1", "", "2:2", "x:y", "-3:"]), label="episodes")
        return [*import_lerobot(Path("{root}"), Path("{out}")), "--episodes", v]
    if which == "sweep":
        opt = data.draw(st.sampled_from(sorted(SWEEP)), label="sweep option")
        return [*sweep_real(Path("{root}"), Path("{out}")), opt, data.draw(SWEEP[opt], label=opt)]
    v = data.draw(st.sampled_from(["0", "-1", "1e9", "nan", "inf"]), label="seconds")
    return [*rollout(Path("{root}"), Path("{out}")), "--rollout.episode-seconds", v]


@BATTERY
@given(data=st.data())
def test_numeric_options_at_their_edges_are_one_line(pristine, data):
    args = option_case(data)
    attack(pristine, lambda root: None,
           lambda root, out: [a.replace("{root}", str(root)).replace("{out}", str(out)) for a in args])


# -- the battery catches what it is for ------------------------------------------------------------------------------
def test_the_battery_catches_a_planted_fault(pristine, monkeypatch):
    """The episode reader's door switched off (np.load as it was): the battery must fail on a truncated array."""
    import sc3_jax.data.episodes as episodes

    monkeypatch.setattr(episodes, "load_npy", lambda path, fix, mmap=False: np.load(path, mmap_mode="r" if mmap
                                                                                      else None))
    with pytest.raises(AssertionError, match="traceback"):
        test_every_damaged_file_kind_ends_in_one_line_and_changes_nothing_outside_out(pristine, "episode arrays")
