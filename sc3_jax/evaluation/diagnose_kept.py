"""Where an object dies: ``sc3 diagnose``'s "kept" table, the benchmark's scene measures (objects, the arm) of
imagined frames over real ones, split into the stages a frame goes through before a policy sees it:

* ``round trip``: the real frame encoded and decoded by the tokenizer (what the model could draw at best);
* ``one chunk``: the frame predicted from real context at most one chunk earlier, with the recorded actions (the
  teacher-forced pass: what one chunk of generation loses);
* ``open loop``: the frame predicted chunk after chunk from the episode's first frames, with the recorded actions
  (what accumulates; its ``per chunk`` column is the geometric decay per chunk between the first and last time);
* closed loop is a policy's: the sweep report's "objects kept" row (``sc3 report``).

Read at :data:`SECONDS` after the last context frame (open-loop step index ``round(s * control_hz)``): a stage that
reads about 1 keeps the measure, toward 0 it loses it. If the round trip already reads low, the tokenizer (or the
image size) is where the object dies; if one chunk is fine and open loop decays, it is the accumulation.
A filmstrip per stage (real above imagined, the first episode, every view, at those times) is written where asked.
numpy only.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from sc3_jax.measures import permanence

SECONDS = (1.0, 2.0, 4.0, 8.0)
STAGES = ("round trip", "one chunk", "open loop")


class Kept:
    """The per-episode amounts of every (stage, measure): (imagined, real) [V, len(SECONDS)] with nan where an
    episode has no frame at a time, and the first episode's frames for the filmstrips."""

    def __init__(self, measures: dict, hz: float, keep: int, num_views: int):
        self.measures, self.keep, self.v = measures, keep, num_views
        self.at = [int(round(s * hz)) for s in SECONDS]
        self.hz = hz
        self.amounts = {(st, m): {} for st in STAGES for m in measures}  # episode -> (im, re) [V, n]
        self.strips: dict[str, tuple[list, list]] = {}

    def _slot(self, stage: str, measure: str, e: int):
        n = len(self.at)
        return self.amounts[(stage, measure)].setdefault(e, (np.full((self.v, n), np.nan),
                                                              np.full((self.v, n), np.nan)))

    def add(self, stage: str, e: int, ks: list[int], imagined: np.ndarray, real: np.ndarray) -> None:
        """Frames [V, len(ks), H, W, 3] of episode ``e`` at open-loop step indices ``ks`` (each in ``self.at``)."""
        if not ks:
            return
        cols = [self.at.index(k) for k in ks]
        for name, measure in self.measures.items():
            im, re = self._slot(stage, name, e)
            im[:, cols], re[:, cols] = measure(imagined), measure(real)
        if e == 0:
            real_f, im_f = self.strips.setdefault(stage, ([None] * len(self.at), [None] * len(self.at)))
            for j, c in enumerate(cols):
                real_f[c], im_f[c] = real[:, j], imagined[:, j]

    def wanted(self, lo: int, hi: int) -> list[int]:
        """The table's step indices in [lo, hi]."""
        return [k for k in self.at if lo <= k <= hi]

    def section(self, views: list[str], seed: int) -> dict:
        labels = {f"{s:g} s": i for i, s in enumerate(SECONDS)}
        rows = []
        for (stage, name), per_ep in self.amounts.items():
            if not per_ep:
                rows.append({"stage": stage, "measure": name, "times": {}})
                continue
            im = np.stack([a for a, _ in per_ep.values()])
            re = np.stack([b for _, b in per_ep.values()])
            row = {"stage": stage, "measure": name,
                   "times": permanence.summary(im, re, labels, views, seed=seed)}
            if stage == "open loop":
                row["per_chunk"] = _per_chunk(row["times"], self.keep / self.hz)
            rows.append(row)
        return {"seconds": list(SECONDS), "rows": rows,
                "closed_loop": "a policy's: the sweep report's objects-kept row (sc3 report)"}

    def write_filmstrips(self, out: str | Path, views: list[str]) -> list[str]:
        """One PNG per stage: per view a real row above an imagined row, a column per time reached."""
        import cv2

        from sc3_jax.core import atomic

        out = Path(out)
        written = []
        for stage, (real, im) in self.strips.items():
            cols = [i for i, f in enumerate(real) if f is not None]
            if not cols:
                continue
            rows = []
            for v in range(len(views)):
                rows += [np.concatenate([real[c][v] for c in cols], 1), np.concatenate([im[c][v] for c in cols], 1)]
            img = np.concatenate(rows, 0)
            scale = max(1, 256 // img.shape[0] + 1)
            img = cv2.resize(img, (img.shape[1] * scale, img.shape[0] * scale), interpolation=cv2.INTER_NEAREST)
            ok, buf = cv2.imencode(".png", cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
            path = out / f"{stage.replace(' ', '_')}.png"
            atomic.write_bytes(path, buf.tobytes())
            written.append(str(path))
        return written


def _per_chunk(times: dict, chunk_s: float) -> float | None:
    """Geometric decay per chunk of the all-views value between the first and the last time reached."""
    pts = [(float(label[:-2]), e["kept"]["all views"]["value"]) for label, e in times.items()]
    pts = [(t, v) for t, v in pts if np.isfinite(v) and v > 0]
    if len(pts) < 2:
        return None
    (t0, v0), (t1, v1) = pts[0], pts[-1]
    return float((v1 / v0) ** (chunk_s / (t1 - t0)))


def round_trip(tokenizer, frames: np.ndarray, image_size) -> np.ndarray:
    """Real frames uint8 [V, n, H, W, 3] encoded and decoded by the world model's tokenizer, uint8. Each frame is its
    own clip: the frames are seconds apart, and a tokenizer that compresses time (a Wan VAE) would merge them."""
    import jax.numpy as jnp

    from sc3_jax.model.tokenizer import to_uint8
    clips = jnp.asarray(frames)[:, :, None]  # [V, n, 1, H, W, 3]
    return np.asarray(to_uint8(tokenizer.decode(tokenizer.encode(clips), tuple(image_size))))[:, :, 0]


def lines(sec: dict) -> tuple[str, list[str]]:
    """The markdown table of :meth:`Kept.section`."""
    if "note" in sec:
        return "", [sec["note"]]
    labels = [f"{s:g} s" for s in sec["seconds"]]

    def cell(e):
        if e is None:
            return "-"
        c = e["kept"]["all views"]
        return f"{c['value']:.2f} [{c['lo']:.2f}, {c['hi']:.2f}]"
    L = ["| measure | stage | " + " | ".join(labels) + " | per chunk |", "|---" * (len(labels) + 3) + "|"]
    for r in sec["rows"]:
        pc = r.get("per_chunk")
        L.append(f"| {r['measure']} | {r['stage']} | " + " | ".join(cell(r["times"].get(x)) for x in labels)
                 + f" | {'-' if pc is None else f'{pc:.2f}'} |")
    L += ["", "Imagined over real, every view together (95% bootstrap over episodes); 1: kept, toward 0: faded. "
          "round trip: the tokenizer alone; one chunk: from real context at most one chunk before; open loop: "
          "chunk after chunk with the recorded actions; closed loop: " + sec["closed_loop"] + "."]
    if sec.get("filmstrips"):
        L.append("Filmstrips (real above imagined, per view): " + ", ".join(sec["filmstrips"]))
    return "", L
