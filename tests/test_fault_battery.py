"""The fault battery: every file kind sc3 reads (episode arrays, dataset.json, results records, a labels CSV, a world
model's config / params / orbax checkpoint, a LeRobot info.json, a store's kept real outcomes) truncated, corrupted
or retyped, and numeric options drawn at their edges, each given to the real command (``sc3_jax.cli.main``, in this
process) that reads it. For every drawn fault: a non-zero exit, exactly one line on stderr, no traceback, the
inputs unchanged and nothing written outside OUT. The faults are drawn by ``hypothesis`` (a failure prints the
example that breaks, and the planted-fault test shows the battery catching a validator switched off)."""
import contextlib
import gzip
import io
import json
import math
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

    from sc3_jax.model import checkpoint

    wm = tiny_world_model(root)
    cfg, _, params = checkpoint.load(wm)
    conv = checkpoint.save_converted(root / "converted", cfg, params)
    shutil.copy(wm / "norm_stats.json", conv / "norm_stats.json")
    return wm


def _ae_world_model(root: Path) -> Path:
    """A world model of a learned (conv_ae) tokenizer, tiny: its config.json, tokenizer/ae.json and
    norm_stats.json are the files of a saved model the door reads (issue 76)."""
    import jax

    from sc3_jax.core.config import load_config, replace
    from sc3_jax.data.norm_stats import NormStats
    from sc3_jax.model import autoencoder as ae
    from sc3_jax.model import checkpoint, dit
    from sc3_jax.model.tokenizer import token_geometry

    acfg = ae.AEConfig(latent_channels=4, downsample=2, width=8, mid_width=8, out_width=4, blocks=1)
    ae.save(root / "tok", acfg, (16, 16), jax.device_get(ae.init(acfg, jax.random.key(0))),
            {"mean": np.zeros(4, np.float32), "std": np.ones(4, np.float32)})
    cfg = replace(load_config("tiny"), model=dict(dim=32, depth=1, num_heads=2, num_kv_heads=1, head_dim=16,
                                                  mlp_dim=64, rope_axes_dim=(4, 2, 2), tokenizer="conv_ae",
                                                  tokenizer_path=str(root / "tok"), patch_size=2, num_views=1,
                                                  action_dim=2),
                  data=dict(views=("cam",), image_size=(16, 16), fps=10.0, state_dim=0))
    token_dim, grid = token_geometry(cfg)
    params = jax.device_get(dit.init_params(cfg.model, token_dim, jax.random.key(0), grid))
    stats = NormStats(np.zeros(2, np.float32), np.full(2, 0.1, np.float32), action_space=ActionSpace("absolute", 2))
    out = checkpoint.save(root / "aewm", cfg, stats, params, np.float32)
    shutil.rmtree(root / "tok")  # the model carries its own copy (aewm/tokenizer)
    return out


def _fitting_store(root: Path, wm: Path) -> Path:
    """A store the world model ``wm`` fits (its views, image size, frame rate and action dimension): a command
    given it goes past the data's checks to the door under test."""
    from sc3_jax.model import checkpoint

    cfg = checkpoint.read_config(wm)
    h, w = cfg.data.image_size
    store = EpisodeStore(root, views=list(cfg.data.views), fps=cfg.data.fps, image_size=(h, w), create=True,
                         action_space=ActionSpace("absolute", cfg.model.action_dim), has_pose=False)
    for i in range(2):
        store.write(Episode(f"e{i}", {v: np.full((12, h, w, 3), 40 * i, np.uint8) for v in cfg.data.views},
                            np.zeros((12, cfg.model.action_dim), np.float32), None, "pick it up"))
    return root


@pytest.fixture(scope="module")
def pristine(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("pristine")
    _store(root / "store")
    _lerobot(root / "lerobot")
    _world_model(root)
    _ae_world_model(root)
    _fitting_store(root / "fit", root / "wm")
    results = root / "results"
    shutil.copytree(DOCS / "stores" / "cmd1_s1", results)
    (results / "results.jsonl").write_bytes(gzip.decompress((results / "results.jsonl.gz").read_bytes()))
    (results / "results.jsonl.gz").unlink()
    (root / "real.csv").write_text("policy,episode,success\nzero,e0,1\nzero,e1,0\n")
    # a sweep of held-out episodes (sweep.json names its policies and conditions), its records unarchived
    episodes = root / "results_ep"
    episodes.mkdir()
    shutil.copy(DOCS / "stores" / "so101_sweep36" / "sweep.json", episodes)
    (episodes / "results.jsonl").write_bytes(
        gzip.decompress((DOCS / "stores" / "so101_sweep36" / "results.jsonl.gz").read_bytes()))
    # initial conditions as sc3 rollout reads an .npz (one condition): the policy is resolved before any rollout
    np.savez(root / "ic.npz", frames=np.zeros((1, 3, 2, 16, 16, 3), np.uint8), state=np.zeros((1, 7), np.float32))
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
        how = data.draw(st.sampled_from(["outcome", "u", "policy", "mode", "cut", "missing", "garbage", "twice",
                                         "negative u"]), label="fault")
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
        elif how == "negative u":  # U_chunk is a distance: a negative one is no U a sweep measured
            key = next((k for k in ("u", "u_raw") if k in r), "u")  # a real record has none: then a layout fault too
            r[key] = [-data.draw(st.floats(1e-6, 10), label="-u")] * len(r.get(key) or [0])
        if how == "twice":  # the same rollout id again, other numbers: the last one silently won
            r["objects"] = [dict(o, placing=not o["placing"]) for o in r["objects"]]
            lines.append(json.dumps(r) + "\n")
        elif how == "cut":  # a complete line cut short (its newline kept): not a kill's cut line, a damaged one
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


def store_files(data):
    """An episode store's file that is not its own regular file: a frames file linked to another store, a FIFO in
    place of an array (which hung the reader), or an .npy whose header claims more rows than the file holds (which
    had numpy ask for terabytes)."""
    how = data.draw(st.sampled_from(["link out", "fifo", "huge header"]), label="fault")
    rel = data.draw(st.sampled_from(EPISODE_FILES), label="file")

    def damage(root: Path):
        p = root / rel
        if how == "link out":
            other = root / "other_store" / p.name
            other.parent.mkdir(exist_ok=True)
            shutil.copy(p, other)  # the same bytes: only where they live is wrong
            p.unlink()
            p.symlink_to(other)
        elif how == "fifo":
            raw = p.read_bytes()
            p.unlink()
            os.mkfifo(p)
            _feed_fifo(p, raw)
        else:
            x = np.load(p)
            rows = data.draw(st.sampled_from([10**11, 10**9, 2 * len(x)]), label="rows")
            with open(p, "wb") as f:  # the header of a longer array, the data of this one
                np.lib.format.write_array_header_1_0(f, {"descr": np.lib.format.dtype_to_descr(x.dtype),
                                                         "fortran_order": False, "shape": (rows, *x.shape[1:])})
                f.write(x.tobytes())
    return damage, export


def _feed_fifo(path: Path, raw: bytes, wait_s: float = 3.0) -> None:
    """Once a reader opens the FIFO (within ``wait_s``), hand it ``raw``: a reader that opens a FIFO then reads a
    whole array and exits 0, which the battery sees, instead of hanging the test forever."""
    import errno
    import threading
    import time

    def feed():
        end = time.monotonic() + wait_s
        while time.monotonic() < end:
            try:
                fd = os.open(path, os.O_WRONLY | os.O_NONBLOCK)
            except OSError as e:
                if e.errno not in (errno.ENXIO, errno.ENOENT):
                    return
                time.sleep(0.05)
                continue
            with contextlib.suppress(OSError):
                os.set_blocking(fd, True)
                os.write(fd, raw)
            os.close(fd)
            return
    threading.Thread(target=feed, daemon=True).start()


def report_default(root, out):
    return ["report", str(root / "results"), "--draws", "10"]  # into the store's own report/


def report_episodes(root, out):
    return ["report", str(root / "results_ep"), "--out", str(out / "report"), "--draws", "10"]


def episode_sweep_records(data):
    """A store of held-out episodes whose records are not of its sweep.json: a record of an episode it does not
    list, of a policy it did not run, an edited policy_names, or the report/ it is written into linked elsewhere."""
    how = data.draw(st.sampled_from(["foreign episode", "foreign policy", "renamed", "report link"]), label="fault")
    i = data.draw(st.integers(0, 30), label="record")

    def damage(root: Path):
        if how == "report link":  # a bench store's report/ linked to files outside it: they would be overwritten
            victim = root / "victim"
            victim.mkdir()
            (victim / "report.md").write_text("not yours to overwrite\n")
            (root / "results" / "report").symlink_to(victim, target_is_directory=True)
            return
        store = root / "results_ep"
        if how == "renamed":
            cfg = json.loads((store / "sweep.json").read_text())
            k = data.draw(st.integers(0, len(cfg["policy_names"]) - 1), label="name")
            cfg["policy_names"][k] = data.draw(st.sampled_from(["so_best", cfg["policy_names"][k - 1]]),
                                               label="as")
            (store / "sweep.json").write_text(json.dumps(cfg))
            return
        p = store / "results.jsonl"
        lines = p.read_text().splitlines(keepends=True)
        r = json.loads(lines[i])
        if how == "foreign episode":
            r["episode"] = data.draw(st.sampled_from(["seed99999999", "elsewhere"]), label="episode")
        else:
            r["policy"] = "not_swept"
            r["id"] = f"not_swept/{r['seed']}_online"
        lines[i] = json.dumps(r) + "\n"
        p.write_text("".join(lines))
    return damage, report_default if how == "report link" else report_episodes


# real.json: the real outcomes a store keeps (issue 76). Per field, values its reader must refuse (an empty given
# list, any episode id, a named policy are values it takes)
KEPT_WRONG = {"format": WRONG, "given": WRONG.filter(lambda v: v != []), "episodes": WRONG,
              "policy": WRONG.filter(lambda v: not (isinstance(v, str) and v)),
              "episode": WRONG.filter(lambda v: not isinstance(v, str)), "outcomes": WRONG}


def _outside(root: Path, which: int) -> str:
    """A real-outcome path outside the store, as a store from before the outcomes were kept names them: the
    inputs' real.csv by its absolute path, relative ones beside the sweep's --out ("sweep"), the system's."""
    return [str(root / "real.csv"), "../real.csv", "sweep/../real.csv", "real.csv", "/etc/hostname"][which]


def kept_real(data):
    """The store's real.json retyped, naming a path outside the store, or linked out of it: refused in one line,
    the path never read (a planted file there once set every policy's real success to 1.0, exit 0)."""
    how = data.draw(st.sampled_from(["retype", "outside", "link out"]), label="fault")

    def damage(root: Path):
        p = root / "results_ep" / "real.json"
        d = json.loads((DOCS / "stores" / "so101_sweep36" / "real.json").read_text())
        if how == "outside":
            d = {"real": [_outside(root, data.draw(st.integers(0, 4), label="path"))]}
        elif how == "retype":
            key = data.draw(st.sampled_from(list(KEPT_WRONG)), label="field")
            at = d if key in ("format", "given", "episodes") else \
                d["episodes"][data.draw(st.integers(0, len(d["episodes"]) - 1), label="episode")]
            value = data.draw(st.one_of(KEPT_WRONG[key], st.just("<missing>")), label=f"{key} =")
            if value == "<missing>":
                at.pop(key)
            else:
                at[key] = value
        p.write_text(json.dumps(d))
        if how == "link out":  # the same outcomes, in a file of another store's
            p.rename(root / "other_real.json")
            p.symlink_to(root / "other_real.json")
    return damage, report_episodes


# norm_stats.json: the statistics and the action space a velocity model integrates its commands with (measured
# state entries, gains, the recorded range); a retyped field here was a traceback, a NaN / negative std or a
# fractional index a model run in other units without a word
STATS_FIELDS = ["mean", "std", "pose_mean", "pose_std", "action_space"]
SPACE_FIELDS = ["measured", "gain", "low", "high"]
_BOTH = ["abc", 5, [None] * 7, [math.nan] * 7, [1] * 3]
SPACE_WRONG = {"measured": [*_BOTH, None, [1.5] * 7, [True] * 7, [math.inf] * 7, [[1]] * 7, [-2] * 7, {"a": 1}],
               "gain": [*_BOTH, None, [math.inf] * 7, [[1]] * 7, {"a": 1}],
               "low": [*_BOTH, [math.inf] * 7, [2.0] * 7], "high": [*_BOTH, [-math.inf] * 7, [-2.0] * 7]}
# WRONG less None: an absent or null action_space is the simulated benchmark's (files from before declarations)
STATS_WRONG = st.one_of(st.sampled_from(["abc", "", [], [1, 2], {}, {"a": 1}, True, -1, 0, 1e308, "nan"]),
                        st.sampled_from([[math.nan] * 7, [-1.0] * 7, [0.0] * 7, [math.inf] * 7, [1.0] * 3,
                                         [[1.0]] * 7, ["a"] * 7]))


def velocity_space(field: str, value) -> dict:
    """A 7-D velocity declaration (the battery model's dimension) whose ``field`` is ``value``."""
    space = {"kind": "velocity", "dim": 7, "names": [f"a{i}" for i in range(7)], "targets": [6],
             "measured": [0, 1, 2, 3, 4, 5, -1], "gain": [1.0] * 7, "low": [-1.0] * 7, "high": [1.0] * 7}
    space[field] = value
    return space


def norm_stats(data):
    how = data.draw(st.sampled_from(["truncate", "retype", "action space"]), label="fault")
    if how == "truncate":
        return truncate("wm/norm_stats.json", data), rollout
    if how == "retype":
        return retype_json("wm/norm_stats.json", STATS_FIELDS, data, STATS_WRONG,
                           optional=["pose_mean", "pose_std", "action_space"]), rollout
    field = data.draw(st.sampled_from(SPACE_FIELDS), label="action_space field")
    value = data.draw(st.sampled_from(SPACE_WRONG[field]), label=f"action_space.{field} =")

    def damage(root: Path):
        p = root / "wm" / "norm_stats.json"
        d = json.loads(p.read_text())
        d["action_space"] = velocity_space(field, value)
        p.write_text(json.dumps(d))
    return damage, rollout


KINDS = {"norm_stats.json": norm_stats, "episode arrays": episode_arrays, "store files": store_files,
         "episode sweep records": episode_sweep_records, "dataset.json": dataset_json, "results records": results_records,
         "labels CSV": labels_csv, "world model": world_model_files, "LeRobot info.json": lerobot_info,
         "kept real outcomes": kept_real}


@pytest.mark.parametrize("kind", list(KINDS))
@BATTERY
@given(data=st.data())
def test_every_damaged_file_kind_ends_in_one_line_and_changes_nothing_outside_out(pristine, kind, data):
    damage, argv = KINDS[kind](data)
    attack(pristine, damage, argv)


@BATTERY
@given(data=st.data())
def test_every_damaged_norm_stats_field_is_refused_where_the_model_is_read(pristine, data):
    """Not only one line from the command: the model's reader itself refuses each drawn fault (the command's line
    could come from a later check), so no rollout ever runs in statistics it cannot trust."""
    from sc3_jax.model import checkpoint
    from sc3_jax.core.errors import UserError

    damage, _ = norm_stats(data)
    with tempfile.TemporaryDirectory() as tmp:
        wm = Path(tmp) / "wm"
        shutil.copytree(pristine / "wm", wm)
        damage(Path(tmp))
        if (wm / "norm_stats.json").read_bytes() == (pristine / "wm" / "norm_stats.json").read_bytes():
            return  # nothing changed (nothing to refuse)
        try:
            checkpoint.read_robot(wm)
        except UserError as e:
            assert "\n" not in str(e) and "norm_stats.json" in str(e), str(e)
        except Exception as e:  # noqa: BLE001  (what a user would see as a traceback)
            raise AssertionError(f"traceback: {type(e).__name__}: {e}") from e
        else:
            raise AssertionError("a damaged norm_stats.json was read as a model's statistics")


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


def _rollout_ic(*extra):
    return lambda root, out: ["rollout", "--world-model", str(root / "wm"), "--policy", "zero", "--data",
                              str(root / "ic.npz"), "--out", str(out / "r"), "--no-video", "--no-progress", *extra]


def _train(*extra):
    return lambda root, out: ["train", "--config", "tiny", "--data", str(root / "store"), "--train.workdir",
                              str(out / "wd"), "--train.no-progress", *extra]


def _import(*extra):
    return lambda root, out: [*import_lerobot(root, out), *extra]


# each of today's faults at the door, by command: one line and nothing written (the last of each argv wins)
DOOR = {
    "rollout --episodes -1": _rollout_ic("--episodes", "-1"), "rollout --start -5": _rollout_ic("--start", "-5"),
    "rollout --batch 0": _rollout_ic("--batch", "0"), "rollout --seed -1": _rollout_ic("--seed", "-1"),
    "rollout --data-fps 0": _rollout_ic("--data-fps", "0"),
    "rollout --policy nosuchname": _rollout_ic("--policy", "nosuchname"),
    "rollout --policy os:getcwd": _rollout_ic("--policy", "os:getcwd"),
    "rollout --out FILE": lambda root, out: [*_rollout_ic()(root, out), "--out", str(root / "real.csv")],
    "rollout --out FILE/x": lambda root, out: [*_rollout_ic()(root, out), "--out", str(root / "real.csv" / "x")],
    "train --batch 0": _train("--batch", "0"), "train --train.steps 0": _train("--train.steps", "0"),
    "train --train.lr nan": _train("--train.lr", "nan"), "train --train.lr -1": _train("--train.lr", "-1"),
    "train --train.lr inf": _train("--train.lr", "inf"), "train --train.b2 1": _train("--train.b2", "1"),
    "train --train.grad-clip 0": _train("--train.grad-clip", "0"),
    "train --train.log-every 0": _train("--train.log-every", "0"),
    "train --modes.probs 0 0 0": _train("--modes.probs", "0", "0", "0"),
    "train --train.workdir FILE": lambda root, out: [*_train()(root, out), "--train.workdir", str(root / "real.csv")],
    "import --image-size 0 -5": _import("--image-size", "0", "-5"),
    "import --image-size 20000 20000": _import("--image-size", "20000", "20000"),
    "import --fps 0": _import("--fps", "0"), "import --fps nan": _import("--fps", "nan"),
    "import --out FILE/x": lambda root, out: [*import_lerobot(root, out)[:-4], "--out", str(root / "real.csv" / "x"),
                                              "--action-space", "absolute"],
    "export --crf 99": lambda root, out: [*export(root, out), "--crf", "99"],
    "report --out FILE": lambda root, out: [*report(root, out), "--out", str(root / "real.csv")],
    # (on a store the model fits: the data's own check would refuse it first, with the scorer's door off too)
    "sweep --scorer os:getcwd": lambda root, out: [*sweep_real(root, out), "--data", str(root / "fit"), "--scorer",
                                                   "os:getcwd"],
    # scripts/probe_faults.py's finds (2026-12-02): each exited 0, was a traceback or hung
    "rollout --rollout.tau -1": _rollout_ic("--rollout.tau", "-1"),
    "rollout --rollout.tau nan": _rollout_ic("--rollout.tau", "nan"),
    "train-tokenizer --steps 0": lambda root, out: _tokenizer(root, out, "--steps", "0"),
    "train-tokenizer --lr nan": lambda root, out: _tokenizer(root, out, "--lr", "nan"),
    "train-tokenizer --batch 0": lambda root, out: _tokenizer(root, out, "--batch", "0"),
    "train-tokenizer --workdir FILE/x": lambda root, out: _tokenizer(root, out, "--workdir",
                                                                     str(root / "real.csv" / "x")),
    "demo --episodes 0": lambda root, out: ["demo", "--out", str(out / "demo"), "--episodes", "0"],
    "demo --steps 0": lambda root, out: ["demo", "--out", str(out / "demo"), "--steps", "0", "--episodes", "1"],
    "demo --out FILE": lambda root, out: ["demo", "--out", str(root / "real.csv"), "--episodes", "1"],
    "serve-policy --num-views 0": lambda root, out: ["serve-policy", "--policy", "zero", "--num-views", "0"],
    # issue 76: a model's sizes, in a config to train as in a saved one (a JAX TypeError)
    "train --model.dim -192": _train("--model.dim", "-192"),
    "train --data.image-size 0 16": _train("--data.image-size", "0", "16"),
}


def _tokenizer(root, out, *extra):
    return ["train-tokenizer", "--data", str(root / "store"), "--workdir", str(out / "tok"), "--steps", "1",
            "--batch", "2", "--eval-frames", "2", "--no-progress", *extra]


def _link_out(rel: str):
    """``rel`` made a link to a directory of the inputs: a command's output there would write into it."""
    def damage(root: Path):
        (root / "victim").mkdir()
        (root / "victim" / "keep.txt").write_text("not yours to overwrite\n")
        (root / rel).symlink_to(root / "victim", target_is_directory=True)
    return damage


def _edit_file(rel: str, edit):
    def damage(root: Path):
        edit(root / rel)
    return damage


def _complex_frames(p: Path):
    with np.load(p) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["frames"] = arrays["frames"].astype(np.complex64)
    np.savez(p, **arrays)


def _link_header_out(p: Path):
    other = p.parent.parent / "other_store_dataset.json"
    shutil.copy(p, other)
    p.unlink()
    p.symlink_to(other)


def _parquet_a_directory(root: Path):
    f = sorted((root / "lerobot" / "meta" / "episodes").rglob("*.parquet"))[0]
    f.unlink()
    f.mkdir()


# damaged inputs the probe found read silently or as a traceback, and outputs that were links written through
FILE_DOOR = {
    "an .npz of complex frames": (_edit_file("ic.npz", _complex_frames), _rollout_ic()),
    "sweep.json a list": (_edit_file("results/sweep.json", lambda p: p.write_text("[1, 2]")), report),
    "dataset.json linked out of its store": (_edit_file("store/dataset.json", _link_header_out), export),
    "a LeRobot episodes parquet that is a directory": (_parquet_a_directory, import_lerobot),
    "import --out a link": (_link_out("link"), lambda root, out: [*import_lerobot(root, out)[:-4], "--out",
                                                                   str(root / "link"), "--action-space", "absolute"]),
    "export --out a link": (_link_out("link"), lambda root, out: [*export(root, out)[:-1], str(root / "link")]),
}


# the line each says (a later check of the same run would otherwise also end in one line)
SAYS = {"an .npz of complex frames": "frames is complex64", "rollout --rollout.tau -1": "--rollout.tau -1.0: a "
        "threshold", "rollout --rollout.tau nan": "--rollout.tau nan: a threshold",
        "export --out a link": "link"}


@pytest.mark.parametrize("case", list(FILE_DOOR))
def test_each_damaged_input_or_linked_output_the_probe_found_is_one_line(pristine, case):
    damage, argv = FILE_DOOR[case]
    line = attack(pristine, damage, argv)
    assert SAYS.get(case, "") in line, line


@pytest.mark.parametrize("case", ["rollout --rollout.tau -1", "rollout --rollout.tau nan"])
def test_a_threshold_that_is_no_threshold_is_refused_before_the_model_loads(pristine, case):
    line = attack(pristine, lambda root: None, DOOR[case])
    assert SAYS[case] in line, line


def test_an_import_resumed_at_another_image_size_is_refused(pristine, tmp_path):
    """The store was reopened and every episode skipped as "already there", at the size they were, exit 0."""
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(_import("--image-size", "8", "8")(pristine, tmp_path)) == 0
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        assert main(_import("--image-size", "4", "4")(pristine, tmp_path)) == 2
    assert "asked for [4, 4]" in err.getvalue() and len(err.getvalue().strip().splitlines()) == 1
    assert EpisodeStore(tmp_path / "store").image_size == (8, 8)


@pytest.mark.parametrize("case", list(DOOR))
def test_each_option_out_of_bounds_is_one_line_before_anything_is_written(pristine, case):
    attack(pristine, lambda root: None, DOOR[case])


def test_a_refused_import_leaves_nothing_so_the_corrected_rerun_runs(pristine, tmp_path):
    """--image-size 0 -5 left a dataset.json that refused the corrected command; now nothing is written first."""
    out = tmp_path / "store"
    with contextlib.redirect_stderr(io.StringIO()):
        assert main(_import("--image-size", "0", "-5")(pristine, tmp_path)) == 2
    assert not out.exists()
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(_import("--image-size", "4", "4")(pristine, tmp_path)) == 0
    assert EpisodeStore(out).image_size == (4, 4)


# -- the battery catches what it is for ------------------------------------------------------------------------------
def test_the_battery_catches_a_planted_fault(pristine, monkeypatch):
    """The episode reader's door switched off (np.load as it was): the battery must fail on a truncated array."""
    import sc3_jax.data.episodes as episodes

    monkeypatch.setattr(episodes, "load_npy", lambda path, fix, mmap=False: np.load(path, mmap_mode="r" if mmap
                                                                                      else None))
    with pytest.raises(AssertionError, match="traceback"):
        test_every_damaged_file_kind_ends_in_one_line_and_changes_nothing_outside_out(pristine, "episode arrays")


def _off(*_a, **_k):
    return None


# each door of issue 66, switched off, and a fault the battery must then catch: (what is switched off, the attack)
PLANTED = {
    "rollout bounds": (["sc3_jax.commands.rollout.check_options"], "rollout --episodes -1"),
    "train bounds": (["sc3_jax.core.validate.train_config"], "train --batch 0"),
    "import bounds": (["sc3_jax.data.lerobot_import.check_options"], "import --image-size 0 -5"),
    "scorer signature": (["inspect.Signature.bind"], "sweep --scorer os:getcwd"),
    "import --out": (["sc3_jax.core.validate.out_dir"], "import --out FILE/x"),
    "report --out": (["sc3_jax.core.validate.out_dir"], "report --out FILE"),
}


@pytest.mark.parametrize("door", list(PLANTED))
def test_the_battery_catches_each_door_switched_off(pristine, monkeypatch, door):
    targets, case = PLANTED[door]
    for t in targets:
        monkeypatch.setattr(t, _off)
    with pytest.raises(AssertionError):
        attack(pristine, lambda root: None, DOOR[case])


def test_the_battery_catches_the_kept_real_outcomes_door_switched_off(pristine, monkeypatch):
    """real.json's paths read wherever they point (as before issue 76): a path outside the store is read, exit 0."""
    from sc3_jax.evaluation import labels

    monkeypatch.setattr(labels, "_inside", lambda p, out: p)
    monkeypatch.setattr(labels, "_within", lambda p, root: True)

    def damage(root: Path):
        (root / "results_ep" / "real.json").write_text(json.dumps({"real": [_outside(root, 0)]}))
    with pytest.raises(AssertionError, match="exit 0"):
        attack(pristine, damage, report_episodes)


def test_the_battery_catches_the_norm_stats_door_switched_off(pristine, monkeypatch):
    """norm_stats.json read as it was before its door (no field checked): the battery fails on its kind."""
    from sc3_jax.data.action_space import ActionSpace
    from sc3_jax.data.norm_stats import NormStats

    def unchecked(path):
        d = json.loads(Path(path).read_text())
        pose = [np.array(d[k], np.float32) if k in d else None for k in ("pose_mean", "pose_std")]
        mean = np.array(d["mean"], np.float32)
        return NormStats(mean, np.array(d["std"], np.float32), *pose,
                         ActionSpace.from_dict(d.get("action_space"), mean.shape[0]))
    monkeypatch.setattr(NormStats, "load", staticmethod(unchecked))
    with pytest.raises((AssertionError, ExceptionGroup)):
        test_every_damaged_norm_stats_field_is_refused_where_the_model_is_read(pristine)


@pytest.mark.parametrize("kind, targets", [
    ("store files", ["sc3_jax.core.validate.regular_file", "sc3_jax.core.validate.npy_fits"]),
    ("episode sweep records", ["sc3_jax.evaluation.report_episodes.check_against_sweep",
                               "sc3_jax.core.validate.out_dir"]),
])
@pytest.mark.slow  # 25-55 s: kept out of the default run's 15 minutes (CI runs -m slow too)
def test_the_battery_catches_the_store_doors_switched_off(pristine, monkeypatch, kind, targets):
    """The store's own regular files (no link out, no FIFO, no header larger than its file) and its records of its
    own sweep: each switched off, the battery fails on the kind that tests it."""
    for t in targets:
        monkeypatch.setattr(t, _off)
    with pytest.raises((AssertionError, ExceptionGroup)):  # hypothesis reports several distinct failures as a group
        test_every_damaged_file_kind_ends_in_one_line_and_changes_nothing_outside_out(pristine, kind)


COMMANDS_WITH_CONFIG = ["train", "diagnose", "rollout", "plan", "report", "sweep episodes", "data import-lerobot"]


@BATTERY
@given(command=st.sampled_from(COMMANDS_WITH_CONFIG),
       option=st.text(alphabet="abcdefghijklmnopqrstuvwxyz-._=", min_size=1, max_size=24))
def test_an_option_no_command_takes_is_one_line_before_anything_runs(command, option, capsys):
    """Any ``--WORD`` a command does not take (its own options and, where it takes them, its config's fields):
    status 2, one line naming it, no traceback, before a model or store is read (none is given)."""
    from sc3_jax.commands import flags
    from sc3_jax.core.config import Config
    from test_cli_flags import TARGETS, _args

    token = "--" + option.lstrip("-")
    known = {flags._name(o) for o in flags.arity(_args(command)) | flags.arity(Config)} | {"--help"}
    if flags._name(token) in known or flags._name(token) in flags.SET_BY_OPTION or token.startswith("--no-"):
        return  # an option some command path takes: not a fault
    rc = main([*TARGETS[command], token, "1"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "Traceback" not in err, (command, token, err)
    assert f"unknown option {flags._name(token)}" in err, (command, token, err)


# -- issue 76: a saved model's every field at the door; the faults of the machine and of a policy server ----------
# (file, field) of a saved model the validator reads (core/saved_model.py); "a.b" nests
SAVED_FIELDS = [("config.json", f) for f in ("model.dim", "model.depth", "model.num_heads", "model.num_kv_heads",
                                              "model.mlp_dim", "model.patch_size", "model.action_dim",
                                              "model.time_embed_dim", "data.image_size", "data.context_frames",
                                              "data.future_frames", "data.views", "data.fps", "sample.steps")] + \
    [("tokenizer/ae.json", f) for f in ("config.latent_channels", "config.downsample", "config.width",
                                        "config.mid_width", "config.out_width", "config.blocks", "image_size")]
# a count: every one a fault (0 too: none of the fields drawn takes it but blocks, which is drawn without it); a
# field missing from config.json keeps its default (configs evolve: the params then say they do not fit), one
# missing from ae.json is a fault
COUNT_FAULTS = [-192, -1, "sixteen", 1.5, True, None, 10**12, [], {}]
SIZE_FAULTS = [[81, 79], [96, 128], [16, -16], [16], ["a", "b"], "16x16", [16.0, 16.0], None, 16]
FIELD_FAULTS = {"data.image_size": SIZE_FAULTS, "image_size": [[17, 16], [0, 16], [32, 32], "x", [16], None],
                "data.views": ["cam", [], ["cam", "cam"], [1], None], "data.fps": ["ten", -1, 0, [], True],
                "config.blocks": [-1, "one", 1.5, None, 10**6, "<missing>"]}


def saved_model_field(data):
    """(damage, rel, field) of a drawn field of the conv_ae model's files set to a drawn value that is a fault."""
    rel, field = data.draw(st.sampled_from(SAVED_FIELDS), label="file, field")
    faults = FIELD_FAULTS.get(field, COUNT_FAULTS + ["<missing>"] * (rel != "config.json"))
    value = data.draw(st.sampled_from(faults), label=f"{field} =")

    def damage(root: Path):
        p = root / "aewm" / rel
        obj = json.loads(p.read_text())
        *path, last = field.split(".")
        d = obj
        for k in path:
            d = d[k]
        if value == "<missing>":
            d.pop(last)
        else:
            d[last] = value
        p.write_text(json.dumps(obj))
    return damage, rel, field


def rollout_ae(root, out):
    """A rollout of the conv_ae model on initial conditions that are not there (an .npz: no store is checked
    first): whatever a field's fault would do, it does before the conditions are read."""
    return ["rollout", "--world-model", str(root / "aewm"), "--policy", "zero", "--data", str(root / "none.npz"),
            "--out", str(out / "r"), "--no-video", "--no-progress"]


@BATTERY
@given(data=st.data())
def test_every_damaged_saved_model_field_is_refused_at_the_door_naming_its_file_and_field(pristine, data):
    """Issue 76: ae.json latent_channels "sixteen" (a 50-line JAX TypeError), config.json model.dim -192 (a JAX
    TypeError), an image size the tokenizer was not trained on (a ValueError traceback): the model's reader refuses
    each drawn fault itself, in one line naming the file and the field, before anything is built from it."""
    from sc3_jax.core.errors import UserError
    from sc3_jax.model import checkpoint

    damage, rel, field = saved_model_field(data)
    with tempfile.TemporaryDirectory() as tmp:
        shutil.copytree(pristine / "aewm", Path(tmp) / "aewm")
        damage(Path(tmp))
        try:
            checkpoint.read_config(Path(tmp) / "aewm")
        except UserError as e:
            said = str(e)
            assert "\n" not in said and rel in said and field.split(".")[-1] in said, said
        except Exception as e:  # noqa: BLE001  (what a user would see as a traceback)
            raise AssertionError(f"traceback: {type(e).__name__}: {e}") from e
        else:
            raise AssertionError(f"{rel} {field} damaged, read as a model")


@BATTERY
@given(data=st.data())
def test_every_damaged_saved_model_field_is_one_line_from_the_command(pristine, data):
    damage, rel, _ = saved_model_field(data)
    assert rel in attack(pristine, damage, rollout_ae)


def _edit_json(rel: str, edit):
    def damage(root: Path):
        p = root / rel
        obj = json.loads(p.read_text())
        edit(obj)
        p.write_text(json.dumps(obj))
    return damage


# the issue's cases as written: (damage, argv, what its line says)
ISSUE76 = {
    "ae.json latent_channels 'sixteen'": (
        _edit_json("aewm/tokenizer/ae.json", lambda d: d["config"].update(latent_channels="sixteen")), rollout_ae,
        'ae.json: config.latent_channels is "sixteen", expected an integer'),
    "config.json model.dim -192": (_edit_json("aewm/config.json", lambda d: d["model"].update(dim=-192)),
                                   rollout_ae, "config.json: model.dim is -192"),
    "config.json image_size [81, 79]": (_edit_json("aewm/config.json", lambda d: d["data"].update(image_size=[81, 79])),
                                        rollout_ae, "data.image_size [81, 79], its tokenizer"),
    "config.json data.views a string": (_edit_json("aewm/config.json", lambda d: d["data"].update(views="cam")),
                                        rollout_ae, "data.views is 'cam', expected tuple"),
    # a run's config.json as --config, data.fps retyped: a TyroWarning printed before the line (attack: one line)
    "train --config with data.fps 'ten'": (
        _edit_json("aewm/config.json", lambda d: d["data"].update(fps="ten")),
        lambda root, out: ["train", "--config", str(root / "aewm" / "config.json"), "--data", str(root / "none"),
                           "--train.workdir", str(out / "wd"), "--train.steps", "1"],
        "data.fps is 'ten', expected float or null"),
    "import --episodes 0:3 of 2 episodes": (lambda root: None, _import("--episodes", "0:3"),
                                            "--episodes asks for episode_index 2, which this dataset does not have"),
    "import of a truncated data parquet": (
        lambda root: [p.write_bytes(p.read_bytes()[:len(p.read_bytes()) // 2])
                      for p in sorted((root / "lerobot" / "data").rglob("*.parquet"))[:1]],
        import_lerobot, "file-000.parquet: not a whole parquet file"),
    "sweep so101 of another robot's model": (
        lambda root: None, lambda root, out: ["sweep", "so101", "--world-model", str(root / "wm"), "--out",
                                              str(out / "so"), "--scorer", "test_fault_battery:score"],
        "the SO-101 simulator renders"),
    "report of a store with sweep.json's kind removed": (_edit_json("results_ep/sweep.json", lambda d: d.pop("kind")),
                                                         report_episodes, 'no "kind"'),
    "report of a store with sweep.json's episodes removed": (
        _edit_json("results_ep/sweep.json", lambda d: d.pop("episodes")), report_episodes, "episodes is missing"),
    "diagnose --filmstrips --benchmark none": (
        lambda root: None, lambda root, out: ["diagnose", "--world-model", str(root / "wm"), "--data",
                                              str(root / "store"), "--filmstrips", str(out / "fs"), "--no-progress"],
        "has no scene measure, so there are no objects-kept filmstrips"),
}


@pytest.mark.parametrize("case", list(ISSUE76))
def test_each_issue_76_case_as_written_is_one_line_and_writes_nothing(pristine, case):
    damage, argv, says = ISSUE76[case]
    line = attack(pristine, damage, argv)
    assert says in line, line


def _fit_rollout(root, out):
    return ["rollout", "--world-model", str(root / "wm"), "--policy", "zero", "--data", str(root / "fit"),
            "--episodes", "1", "--out", str(out / "r"), "--no-video", "--no-progress"]


def test_an_emptied_episode_directory_is_named_not_passed_over(pristine):
    """Issue 76: `sc3 rollout --episodes 1` on a store whose first episode was emptied rolled out the next one."""
    def empty_e0(root):
        shutil.rmtree(root / "fit" / "e0")
        (root / "fit" / "e0").mkdir()
    line = attack(pristine, empty_e0, _fit_rollout)
    assert "fit/e0: an episode directory without its meta.json" in line, line


def test_a_config_image_size_the_data_lacks_is_one_line_before_the_params_load(pristine, monkeypatch):
    """Issue 76: config.json image_size [96, 128] against 64x64 data ended in a params.npz shape error (a pixel
    tokenizer) or a ValueError traceback (a learned one); now the data and the model are compared first."""
    from sc3_jax.model import checkpoint

    monkeypatch.setattr(checkpoint, "load_params", lambda *a, **k: pytest.fail("the params loaded first"))
    resize = _edit_json("wm/config.json", lambda d: d["data"].update(image_size=[96, 128]))
    line = attack(pristine, resize, _fit_rollout)
    assert "data.image_size=[96, 128], but" in line and "fit/dataset.json has image_size" in line, line


def test_a_policy_server_that_is_not_there_is_one_line_in_every_command_that_connects(pristine, monkeypatch):
    """Issue 76: `sc3 rollout --policy ws://127.0.0.1:1` was 21 lines ending in PolicyConnectionError (`sc3 sweep`
    said it in one); the client's back-off is not waited here."""
    from sc3_jax.policies import openpi_client

    init = openpi_client.WebsocketClientPolicy.__init__
    monkeypatch.setattr(init, "__kwdefaults__", {**init.__kwdefaults__, "backoff_s": 0.0, "max_retries": 1})
    line = attack(pristine, lambda root: None, _rollout_ic("--policy", "ws://127.0.0.1:1"))
    assert line.startswith("sc3 rollout: error: --policy ws://127.0.0.1:1: could not connect to the policy server "
                           "at 127.0.0.1:1") and "is a policy server" in line, line


def test_a_policy_server_fault_mid_run_is_one_line_from_any_command(monkeypatch, capsys):
    """A server that dies or answers an error in the middle of a run (openpi sends a traceback as its text):
    the command's one line, its first and last words, not the client's traceback."""
    from sc3_jax import cli
    from sc3_jax.policies.openpi_client import PolicyServerError

    def fails(argv):
        raise PolicyServerError("error in the policy server at 10.0.0.2:8000:\nTraceback (most recent call last):\n"
                                "  File \"policy.py\", line 3\nValueError: image must be 224x224")
    monkeypatch.setitem(cli.COMMANDS, "rollout", fails)
    assert cli.main(["rollout"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["sc3 rollout: error: error in the policy server at 10.0.0.2:8000: ValueError: image must be "
                   "224x224"], err


@pytest.mark.parametrize("platforms", ["bogus", "gpu"])
def test_a_jax_platform_this_machine_lacks_is_one_line(pristine, tmp_path, platforms):
    """Issue 76: JAX_PLATFORMS=gpu | cuda | bogus on a machine without that backend: chained tracebacks, or a bare
    AssertionError. (A machine with a GPU has gpu: only bogus is asked of it.)"""
    import subprocess
    import sys

    if platforms == "gpu" and any(Path("/dev").glob("nvidia[0-9]*")):
        pytest.skip("this machine has a GPU")
    env = {**os.environ, "JAX_PLATFORMS": platforms}
    r = subprocess.run([sys.executable, "-m", "sc3_jax.cli", *_rollout_ic()(pristine, tmp_path)], env=env,
                       capture_output=True, text=True, timeout=300)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1, r.stderr[-3000:]
    assert lines[0].startswith(f"sc3 rollout: error: JAX_PLATFORMS={platforms}: no such backend") and \
        "cpu always works" in lines[0], lines
    assert not (tmp_path / "r").exists()
