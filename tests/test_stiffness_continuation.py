"""Stiffness continuation: Newton converges for barriers too soft for their load (issue 13).

A barrier of stiffness kappa holds a pair carrying a force f at d ~ 2 kappa dhat^4 / f. With the
paper scenes' kappa (PolyFEM's ``barrier_stiffness`` as written) the pairs rest ~1e-12 m apart
while a step moves them ~1e-3 m along each other, and the collision check cuts every Newton
step: the fig14 puzzle piece thrown at v0 = (2, -0.4) m/s failed at step 12 after 100 Newton
iterations (98 cut, the last to 4.3e-6 of the Newton step; measured before this change). A
solve that stalls (30 cut steps in a row) or fails now solves the step again from its initial
guess through stiffer barriers (factors from the contact forces, about 100x apart) down to the
scene's own; the state reached is a minimiser of the step's own potential, so values and
gradients are those of the direct solve where that converges.
"""

import os
from pathlib import Path

import ipctk
import numpy as np
import pytest
from contact_checks import IntersectionMonitor
from mpi4py import MPI

import diffsolids as ds
from diffsolids.contact import ContactTerm
from diffsolids.contact.diagnostics import continuation_schedule, settling_gap
from diffsolids.controls import FrictionControl, InitialCondition, RigidVelocity
from diffsolids.mesh.scene import combine_meshes, simplex_box
from diffsolids.objectives import center_of_mass, final_value
from diffsolids.reduced_functional import ReducedFunctional

COMM = MPI.COMM_WORLD
DATA = Path(
    os.environ.get("DIFFSOLIDS_DATA", Path(__file__).resolve().parents[2] / "shared" / "data")
)
DHAT = 1e-3
# the block rests ~5e-8 m (5e-5 dhat) above the slab: soft enough for a continuation to be
# offered (below 1e-4 dhat), stiff enough for finite differences (coordinate ulps ~1e-17 m)
KAPPA = 3e5
STEPS = 8


def test_schedule_starts_at_a_comfortable_gap_and_walks_down_to_kappa():
    kappa, dhat, force = 1e5, 3.39e-4, 4.5e3  # the puzzle's step 12 at the scene's kappa
    factors = np.array(continuation_schedule(kappa, dhat, force))
    assert len(factors) >= 2 and np.all(factors > 1.0) and np.all(np.diff(factors) < 0)
    start_gap = settling_gap(kappa * factors[0], dhat, force)
    assert start_gap == pytest.approx(1e-2 * dhat)
    steps = np.concatenate([factors[:-1] / factors[1:], [factors[-1]]])
    assert np.all(steps <= 100.0 * (1 + 1e-12))
    # a barrier whose pairs settle within 1e-4 dhat of the load is left alone
    assert continuation_schedule(1e5 * 1e6, dhat, force) == ()


def block_scene(comm: MPI.Comm, continuation_after: int, rtol: float = 1e-9):
    """A block thrown down and along a slab (BDF1, friction 0.5) under a soft barrier."""
    slab = simplex_box([[0, 0], [1, 0.1]], [10, 1])
    block = simplex_box([[0.1, 0.1 + 0.5 * DHAT], [0.2, 0.15 + 0.5 * DHAT]], [4, 2])
    dom = combine_meshes(comm, [slab, block], names={"slab": 1, "block": 2})
    model = ds.Model(dom, ds.NeoHookean(E=1e6, nu=0.3, density=1000.0))
    model.add_gravity(9.81)
    model.add_dirichlet(lambda x: x[1] < 0.1 + 1e-9, 0.0)
    contact = ContactTerm(
        model, dhat=DHAT, stiffness=KAPPA, friction=0.5, eps_v=1e-3, area_weighting=False
    )
    model.add_numeric_term(contact)
    X = model.V.tabulate_dof_coordinates()[:, :2]
    v0 = np.zeros_like(X)
    v0[X[:, 1] > 0.1 + 1e-9] = [0.5, -0.3]
    options = ds.SolverOptions(rtol=rtol, continuation_after=continuation_after)
    sim = ds.Simulation(model, ds.BDF(1, 0.02, STEPS), options, v0=v0.ravel())
    cx, cy = center_of_mass(model, "block")
    controls = [InitialCondition(sim, "velocity"), FrictionControl(contact, [("slab", "block")])]
    rf = ReducedFunctional(sim, final_value(cx) + 5 * final_value(cy), controls)
    return rf, sim, contact


def _run(continuation_after: int, comm: MPI.Comm = COMM, rtol: float = 1e-9):
    rf, sim, contact = block_scene(comm, continuation_after, rtol)
    q = rf.initial_parameters()
    J, g = rf.value_and_gradient(q)
    gaps = [r.min_distance for r in contact.records]
    return rf, q, J, g, sim.solver.continued_steps, gaps


def test_continuation_reaches_the_direct_minimiser():
    """Continuation after 1 cut step (stages split) vs the direct solve: the same value and
    gradient."""
    _, _, J_direct, g_direct, continued_direct, gaps = _run(30, rtol=1e-12)
    assert continued_direct == 0
    assert max(gaps[2:]) < 1e-4 * DHAT  # soft: the block rests far inside dhat
    rf, _, J, g, continued, _ = _run(1, rtol=1e-12)
    assert continued >= STEPS // 2
    # stages stopped after continuation_after = 1 iteration are split (ContinuationPath.split)
    assert rf.simulation.solver.split_stages >= 1
    assert abs(J - J_direct) <= 1e-10 * abs(J_direct)
    assert np.abs(g - g_direct).max() <= 1e-9 * np.abs(g_direct).max()


def test_loose_stages_and_expanded_steps_save_iterations(monkeypatch):
    """The stages before the last end at 1e-2 f_char, and uncut steps are doubled while the
    potential falls: the continued steps reach the direct minimiser in fewer iterations than
    with every stage converged to rtol and plain Newton steps (measured: 273 -> 189)."""
    import diffsolids.solvers.newton as newton

    _, _, J_direct, _, _, _ = _run(30, rtol=1e-12)
    rf, _, J, _, continued, _ = _run(1, rtol=1e-12)
    its = sum(r.iterations for r in rf.trajectory.records)
    monkeypatch.setattr(newton, "_STAGE_RTOL", 0.0)
    monkeypatch.setattr(newton, "_EXPAND_DOUBLINGS", 0)
    rf_plain, _, J_plain, _, continued_plain, _ = _run(1, rtol=1e-12)
    its_plain = sum(r.iterations for r in rf_plain.trajectory.records)
    assert continued == continued_plain >= STEPS // 2
    assert its < 0.8 * its_plain, (its, its_plain)
    for value in (J, J_plain):
        assert abs(value - J_direct) <= 1e-10 * abs(J_direct)


def test_gradient_through_continued_steps_against_central_differences():
    rf, q, _, g, continued, _ = _run(continuation_after=1, rtol=1e-12)
    assert continued >= STEPS // 2
    d = np.random.default_rng(3).normal(size=q.size)
    h = 1e-4
    for dq in (d / np.linalg.norm(d), g / np.linalg.norm(g)):
        fd = (rf(q + h * dq) - rf(q - h * dq)) / (2 * h)
        adjoint = float(g @ dq)
        # J's round-off here is ~1e-11 (pairs 5e-8 m apart), the same without continuation
        assert abs(fd - adjoint) <= 1e-5 * abs(adjoint), (fd, adjoint)


def test_puzzle_at_the_scene_kappa_converges():
    """The quoted case: fig14 at kappa 1e5 (as PolyFEM reads the scene), v0 = (2, -0.4)."""
    from demo_modules import load_demo

    common = load_demo("paper_common")
    folder = DATA / "diffipc" / "fig14_puzzle_piece"
    if not (folder / "opt.json").is_file():
        pytest.skip(f"the paper's data is not at {folder.parent} (set DIFFSOLIDS_DATA)")
    path, opt = common.experiment(folder.parent, folder.name)
    scene, _ = common.scenes(path, opt)
    _, contact, sim = common.build(scene, COMM, 13, "scene")
    assert contact.stiffness == 1e5
    RigidVelocity(sim, 1, angular=False).assign(np.array([2.0, -0.4]))
    monitor = IntersectionMonitor(sim, contact)
    traj = sim.run()
    assert sim.solver.continued_steps >= 1
    assert monitor.bad == []
    s = contact.surface
    for u in traj.u:
        x = np.asfortranarray(s.rest_positions + s.gather(u))
        assert not ipctk.has_intersections(s.mesh, x)
    gaps = [r.min_distance for r in contact.records if r.num_collisions]
    assert gaps and min(gaps) < 1e-10  # the scene's soft barrier: pairs ~1e-12 m apart


def run_paper_scene(folder: str, steps: int, kappa: float):
    """The paper's experiment ``folder`` at its own barrier stiffness, run for ``steps``
    steps from opt.json's start; every state checked for intersections."""
    from diffsolids.polyfem import read_polyfem_optimization

    opt_json = DATA / "diffipc" / folder / "opt.json"
    if not opt_json.is_file():
        pytest.skip(f"the paper's data is not at {opt_json.parent.parent} (set DIFFSOLIDS_DATA)")
    problem = read_polyfem_optimization(opt_json).build(COMM, steps=steps, stiffness=None)
    sim = problem.rf.simulation
    (contact,) = [t for t in sim.model.numeric_terms if isinstance(t, ContactTerm)]
    assert contact.stiffness == kappa
    problem.rf.controls.assign(problem.q0)
    traj = sim.run()
    s = contact.surface
    for u in traj.u:
        x = np.asfortranarray(s.rest_positions + s.gather(u))
        assert not ipctk.has_intersections(s.mesh, x)
    return sim, contact, traj


def test_bouncing_ball_at_the_scene_kappa_converges():
    """Fig. 22 at kappa 1e4 (the scene's, as PolyFEM reads it): its impact steps need every cut
    step of the stiffer continuation stages extended (step 4 failed after 184 iterations,
    153 of them cut, when only long streaks of small cuts were)."""
    sim, contact, _ = run_paper_scene("fig22_bounce_ball", 5, 1e4)
    assert sim.solver.continued_steps >= 3  # steps 2-5 carry the impact
    # each impact step's first Newton iterations press a pair down to the step bound's gap
    # floor: the continuation starts there, not after continuation_after cut steps
    assert sim.solver.floor_continuations == sim.solver.continued_steps
    gaps = [r.min_distance for r in contact.records if r.num_collisions]
    assert gaps and max(gaps) < 1e-10  # pairs rest ~1e-12 m apart


def test_throw_at_the_scene_kappa_converges():
    """Fig. 1 at kappa 1e5 (the scene's): its first 5 steps converge through continuations.
    In step 5 the continuation's third stage (factor 47, from the converged factor-2.2e3
    state) crawled with full projected steps: before stages were split, it ran 100 iterations
    and the step failed after 276; then it went through factor 320 first. With the collision
    sets built whole where the CCD segment's candidates are many (round-off), that stage no
    longer crawls; the block scene's continued steps split stages
    (test_continuation_reaches_the_direct_minimiser)."""
    sim, _, traj = run_paper_scene("fig1_bunnies", 5, 1e5)
    assert sim.solver.continued_steps >= 3
    assert max(r.iterations for r in traj.records) < 2 * sim.solver.options.max_iterations
