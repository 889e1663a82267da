"""The wall search starts from the observed horizontal velocity when the base throw is too slow.

A base fit without a wall can explain a body that a wall stopped by a slow throw; its trajectory
then reaches no wall placement and every placement scores about zero. The scene (the ``tiny``
hidden-wall slide: a box thrown at 1.5 m/s along x onto a frictionless ground, a rigid wall 24 cm
ahead) is fitted with the base model once; the tests then put the base's v0.x at 0.4 m/s, as
the full-size base fit did (0.41 for 1.5), and compare the search with and without the second
start.
"""

from __future__ import annotations

import numpy as np
import pytest

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("one_torch_thread")]

SLOW_VX = 0.4  # m/s: the full-size base fit's horizontal v0 on the medium-wall slide


@pytest.fixture(scope="module")
def wall_lib(tmp_path_factory):
    from toolkit.discovery.hidden import HiddenScene, fit_base
    from toolkit.discovery.library import LibraryModel

    root = tmp_path_factory.mktemp("discovery_wall")
    hs = HiddenScene("wall", "high")
    scene = hs.generate(root / "scenes" / hs.name)
    inp = hs.physics_input(scene)
    module = fit_base(inp, root / "runs" / hs.name / "physics")
    return LibraryModel(module), hs


def _search(lib, q):
    from toolkit.discovery import ranking as rk

    lib.assign(q)
    r0 = lib.residuals(q)
    Q = rk._projector(lib.jacobian(q, lib.base_names, r0))
    r_perp = rk._perp(Q, r0.numpy())
    L0 = 0.5 * float(r0.numpy() @ r0.numpy())
    return rk._wall_search(lib, q, Q, r_perp, L0), Q, r_perp, L0


def test_horizontal_start_is_the_observed_throw(wall_lib):
    """The second start keeps the base's v0.y and material and sets v0.x, v0.z to the observed
    body's straight-line velocity before the wall: within 0.25 m/s of the true (1.5, 0.3); it is
    ``None`` when the base already moves that way."""
    from toolkit.discovery.ranking import horizontal_start

    lib, hs = wall_lib
    q = lib.q0.copy()
    q[lib.index_of["v0.x"]] = SLOW_VX
    qh = horizontal_start(lib, q)
    assert qh is not None
    vx, vy, vz = (qh[lib.index_of[f"v0.{a}"]] for a in "xyz")
    assert vx == pytest.approx(1.5, abs=0.25) and vz == pytest.approx(0.3, abs=0.1)
    assert vy == q[lib.index_of["v0.y"]]
    others = [i for i in range(len(q)) if i not in (lib.index_of["v0.x"], lib.index_of["v0.z"])]
    assert np.array_equal(qh[others], q[others])
    assert horizontal_start(lib, qh) is None


def test_wall_search_reaches_the_wall_from_a_slow_base(wall_lib, monkeypatch):
    """From the slow base, the base start alone finds no wall worth a tenth of the loss; with the
    observed-v0 start the search finds the true wall (normal -x, offset within 3 cm of -0.24 m)
    and scores it above 0.2, crediting the wall only beyond the v0 change alone."""
    from toolkit.discovery import ranking as rk

    lib, hs = wall_lib
    q = lib.q0.copy()
    q[lib.index_of["v0.x"]] = SLOW_VX
    with monkeypatch.context() as m:
        m.setattr(rk, "horizontal_start", lambda lib, q0: None)
        (without, *_), *_ = _search(lib, q)
    assert without.search["start"] == "base" and without.score < 0.1, without
    (sc, change, _, where), Q, r_perp, L0 = _search(lib, q)
    assert sc.search["start"] == "observed_v0"
    assert sc.search["normal"] == [-1.0, 0.0, 0.0] and sc.search["offset"] == pytest.approx(-0.24, abs=0.03)
    assert sc.score > 0.2 and sc.score > 2 * without.score
    # the score is the drop below the better of the base and the observed v0 without a wall
    qh = rk.horizontal_start(lib, q)
    rh = rk._perp(Q, lib.residuals(qh).numpy())
    ref = min(float(r_perp @ r_perp), float(rh @ rh))
    rj = change + r_perp
    assert sc.score == pytest.approx(0.5 * (ref - float(rj @ rj)) / L0, rel=1e-6)
    assert sc.search["v0"][0] == pytest.approx(qh[lib.index_of["v0.x"]])


def test_wall_refit_starts_from_the_searched_v0(wall_lib):
    """The confirmation refit of a wall found from the observed-v0 start begins at that v0: its
    start objective is the searched point's, below the slow base's objective with the wall."""
    from toolkit.discovery.confirm import Refit
    from toolkit.discovery.refits import refit_candidate

    lib, hs = wall_lib
    q = lib.q0.copy()
    q[lib.index_of["v0.x"]] = SLOW_VX
    (sc, _, _, where), *_ = _search(lib, q)
    base = Refit(name="base", q=q, start_objective=lib.objective(q), objective=lib.objective(q), iterations=0,
                 rollouts=0, lib=lib)
    rf = refit_candidate(lib, None, {"wall": where}, sc, base, iterations=0)
    start = q.copy()
    start[lib.index_of["wall.strength"]] = sc.search["strength"]
    for a, v in zip("xyz", sc.search["v0"]):
        start[lib.index_of[f"v0.{a}"]] = v
    lib.assign(start)
    assert rf.start_objective == pytest.approx(lib.objective(start), rel=1e-6)
    slow_wall = q.copy()
    slow_wall[lib.index_of["wall.strength"]] = sc.search["strength"]
    lib.assign(slow_wall)
    assert rf.start_objective < lib.objective(slow_wall)
    assert rf.q[lib.index_of["v0.x"]] == pytest.approx(sc.search["v0"][0], abs=1e-9)
