"""How far a scorer agrees with real outcomes on real frames (``sc3 check-scorer``): the scorer a sweep scores
imagined rollouts with is run on a store's labelled real episodes -- their recorded frames and state, exactly as a
sweep hands it imagined ones (a ``RolloutView``) -- and its verdict compared with each episode's label. A scorer
that disagrees with the labels on real frames cannot be trusted on imagined ones, so this is the check to run before
a sweep (issue: "a scorer you can trust on real frames first")."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from sc3_jax.core.errors import UserError


def check(store: str | Path, scorer: str, criterion: str = "success", progress: bool = True) -> dict:
    """{"n", "agreement", "interval" (Wilson 95%), "scorer_done", "labels_done", "false_done", "missed",
    "disagree": [episode ids]} for ``scorer`` (any ``--scorer`` spelling) on every episode of ``store`` (labels as
    ``sc3 sweep episodes --real`` reads them: ``labels.py``)."""
    from tqdm import tqdm

    from sc3_jax.data.episodes import EpisodeStore
    from sc3_jax.evaluation import labels
    from sc3_jax.evaluation.scorers import RolloutView, check_outcomes, load_outcome_scorer
    from sc3_jax.stats.interval import wilson

    if not (Path(store) / "dataset.json").is_file():  # said as this command's option, not as --real's
        raise UserError(f"--data {store}: not an episode store (no dataset.json); import one with `sc3 data "
                        "import-lerobot`")
    real = labels.read([f"real={store}"])
    missing = [e for e in real if criterion not in e.outcomes]
    if missing:
        raise UserError(f"{missing[0].episode}: no label {criterion!r} (its labels: {sorted(missing[0].outcomes)}); "
                        "pass --criterion NAME")
    score = load_outcome_scorer(scorer)
    eps = EpisodeStore(store)
    said, truth, disagree = [], [], []
    for e in tqdm(real, desc="check-scorer", unit="episode", disable=not progress):
        eid = e.episode.rsplit(":", 1)[-1]
        ep = eps.load(eid)
        view = RolloutView(eid, np.stack([ep.frames[v] for v in eps.views]), state=ep.state,
                           instruction=ep.prompt)
        got = check_outcomes(scorer, score(view), eid)
        if criterion not in got:
            raise UserError(f"--scorer {scorer!r}: criteria {sorted(got)}; the labels' is {criterion!r}: pass "
                            "--criterion NAME")
        said.append(got[criterion])
        truth.append(e.outcomes[criterion])
        if said[-1] != truth[-1]:
            disagree.append(eid)
    n, agree = len(said), sum(s == t for s, t in zip(said, truth))
    return {"store": str(store), "scorer": scorer, "criterion": criterion, "n": n, "agreement": agree / n,
            "interval": wilson(agree, n), "scorer_done": sum(said), "labels_done": sum(truth),
            "false_done": sum(s and not t for s, t in zip(said, truth)),
            "missed": sum(t and not s for s, t in zip(said, truth)), "disagree": disagree}
