"""Ground-truth criteria on hand-built states (no physics, no rendering)."""
import numpy as np
import pytest

import sc3_jax.benchmarks.bussing  # noqa: F401  (picks the GL backend before MuJoCo is imported)

pytest.importorskip("mujoco")

from sc3_jax.benchmarks.bussing import criteria as C  # noqa: E402
from sc3_jax.benchmarks.bussing.scene import BIN_WALL_H, CAN_INNER  # noqa: E402
from sc3_jax.benchmarks.bussing.tasks import OBJECT_BY_NAME, destination, make_initial_condition  # noqa: E402

BIN = np.array([0.2, -0.13])
CAN = np.array([0.2, 0.13])
CONTAINERS = {"bin": BIN, "can": CAN}
HH = OBJECT_BY_NAME["cup"].half_height


def _path(*points, n=10):
    """Piecewise-linear trajectory through the given xyz points."""
    pts = [np.asarray(p, float) for p in points]
    segs = [np.linspace(a, b, n) for a, b in zip(pts[:-1], pts[1:])]
    return np.concatenate(segs)


def test_success_lifted_and_placed_in_instructed_container():
    traj = _path([0.0, 0.0, HH], [0.0, 0.0, 0.17], [BIN[0], BIN[1], 0.17], [BIN[0], BIN[1], 0.008 + HH])
    o = C.evaluate_object("cup", traj, HH, "bin", CONTAINERS)
    assert (o.language, o.lifting, o.placing, o.outcome) == (True, True, True, "no failure")
    assert o.final_container == "bin"


def test_object_in_wrong_bin_is_a_language_failure():
    traj = _path([0.0, 0.0, HH], [0.0, 0.0, 0.17], [CAN[0], CAN[1], 0.17], [CAN[0], CAN[1], 0.008 + HH])
    o = C.evaluate_object("cup", traj, HH, "bin", CONTAINERS)
    assert not o.language and o.lifting and not o.placing
    assert o.outcome == "language"
    assert o.final_container == "can"


def test_wrong_container_visited_then_moved_still_violates_language():
    traj = _path([0.0, 0.0, HH], [CAN[0], CAN[1], 0.17], [CAN[0], CAN[1], 0.02 + HH], [CAN[0], CAN[1], 0.17],
                 [BIN[0], BIN[1], 0.17], [BIN[0], BIN[1], 0.008 + HH])
    o = C.evaluate_object("cup", traj, HH, "bin", CONTAINERS)
    assert o.outcome == "language" and o.placing


def test_dropped_object_is_a_placing_failure():
    # lifted, carried, dropped on the table between the containers
    traj = _path([0.0, 0.0, HH], [0.0, 0.0, 0.17], [0.1, 0.0, 0.17], [0.1, 0.0, HH])
    o = C.evaluate_object("cup", traj, HH, "bin", CONTAINERS)
    assert (o.language, o.lifting, o.placing) == (True, True, False)
    assert o.outcome == "placing" and o.final_container is None


def test_never_lifted_is_a_lifting_failure():
    traj = np.tile([[-0.1, 0.05, HH]], (50, 1))
    o = C.evaluate_object("cup", traj, HH, "bin", CONTAINERS)
    assert (o.language, o.lifting, o.placing, o.outcome) == (True, False, False, "lifting")


def test_pushed_along_table_is_not_lifted():
    traj = _path([-0.1, 0.0, HH], [0.05, 0.05, HH + 0.01])
    assert not C.evaluate_object("cup", traj, HH, "bin", CONTAINERS).lifting


def test_held_or_moving_at_end_is_not_placed():
    traj = _path([0.0, 0.0, HH], [0.0, 0.0, 0.17], [BIN[0], BIN[1], 0.17], [BIN[0], BIN[1], 0.03])
    assert not C.evaluate_object("cup", traj, HH, "bin", CONTAINERS, held_at_end=True).placing
    assert not C.evaluate_object("cup", traj, HH, "bin", CONTAINERS, final_speed=1.0).placing
    assert C.evaluate_object("cup", traj, HH, "bin", CONTAINERS, final_speed=0.0).placing


def test_inside_container_geometry():
    assert C.inside_container(np.array([CAN[0], CAN[1], 0.03]), CAN, "can")
    assert not C.inside_container(np.array([CAN[0] + CAN_INNER + 0.01, CAN[1], 0.03]), CAN, "can")
    assert not C.inside_container(np.array([BIN[0], BIN[1], BIN_WALL_H + C.RIM_MARGIN + 0.05]), BIN, "bin")
    batch = np.array([[BIN[0], BIN[1], 0.02], [0.0, 0.0, 0.02]])
    np.testing.assert_array_equal(C.inside_container(batch, BIN, "bin"), [True, False])


def test_outcome_order_and_rates():
    assert C.outcome_category(False, False, False) == "language"
    assert C.outcome_category(True, False, False) == "lifting"
    assert C.outcome_category(True, True, False) == "placing"
    assert C.outcome_category(True, True, True) == "no failure"
    rows = [C.ObjectOutcome("a", "bin", True, True, True, "no failure", "bin"),
            C.ObjectOutcome("b", "bin", True, False, False, "lifting", None),
            C.ObjectOutcome("c", "can", False, True, False, "language", "bin"),
            C.ObjectOutcome("d", "can", True, True, False, "placing", None)]
    r = C.success_rates(rows)
    assert r["language"] == 0.75 and r["lifting"] == 0.75 and r["placing"] == 0.25
    assert r["outcome/lifting"] == 0.25 and r["outcome/no failure"] == 0.25 and r["n_objects"] == 4


def test_tasks_destinations_and_initial_conditions():
    assert destination("utensil", "bussing") == "bin" and destination("trash", "bussing") == "can"
    assert destination("utensil", "reverse") == "can" and destination("trash", 1) == "bin"
    a, b = make_initial_condition(5, "bussing"), make_initial_condition(5, "bussing")
    np.testing.assert_array_equal(a.object_xy, b.object_xy)
    assert a.objects == b.objects and a.prompt == b.prompt
    r = make_initial_condition(5, "reverse")
    np.testing.assert_array_equal(a.object_xy, r.object_xy)  # same table, other instruction
    assert a.prompt != r.prompt
    for n in a.objects:
        assert a.destinations()[n] != r.destinations()[n]
    c = make_initial_condition(6, "bussing")
    assert not np.allclose(a.object_xy[:1], c.object_xy[:1]) or a.objects != c.objects


def test_evaluate_episode_uses_instruction():
    ic = make_initial_condition(3, "reverse")
    n = len(ic.objects)
    traj = np.tile(np.concatenate([ic.object_xy, np.full((n, 1), 0.02)], 1)[None], (5, 1, 1))
    outs = C.evaluate_episode(ic, traj)
    assert [o.outcome for o in outs] == ["lifting"] * n
    assert [o.destination for o in outs] == [ic.destinations()[x] for x in ic.objects]


def test_prompts_are_grammatical_for_every_template_and_object_count():
    import itertools
    import re

    from sc3_jax.benchmarks.bussing.tasks import N_TEMPLATES, OBJECT_NAMES, make_prompt
    assert make_prompt(["spoon", "bottle", "lid"], "bussing", template=1) == (
        "Clear the table. The yellow spoon goes in the bin; the blue bottle and the purple lid go in the trash.")
    assert make_prompt(["cup", "bowl", "bag"], "reverse", template=2) == (
        "Swap the usual places: the green bag goes in the utensil bin and the red cup and the orange bowl go in the "
        "trash can.")
    obj = "the (?:" + "|".join(OBJECT_BY_NAME[n].words for n in OBJECT_NAMES) + ")"
    subject_verb = re.compile(rf"({obj}(?:(?:, | and ){obj})*) (goes|go) in")
    checked = 0
    for task in ("bussing", "reverse"):
        for tpl in range(N_TEMPLATES):
            for k in range(1, len(OBJECT_NAMES) + 1):
                for names in itertools.combinations(OBJECT_NAMES, k):
                    p = make_prompt(list(names), task, template=tpl)
                    assert p[0].isupper() and p.endswith(".") and "  " not in p and "nothing" not in p, p
                    for n in OBJECT_NAMES:  # every object on the table is named once, no other
                        assert p.count(OBJECT_BY_NAME[n].words) == (n in names), (p, n)
                    for subject, verb in subject_verb.findall(p.lower()):
                        assert (verb == "goes") == (subject.count("the ") == 1), p
                        checked += 1
                    assert not re.search(r"[;,] [A-Z]", p), p  # no capital after a clause break
    assert checked > 100  # the agreement check ran on the templates with a verb
