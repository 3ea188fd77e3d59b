"""tt.MPC: what one control step applies, the warm start and its reset, batching, and closed-loop episodes.

Default run: the policy's contract (first control of tt.solve from the shifted warm start, clamped), per-instance
resets under a vector environment's autoreset, failure isolation, seeded determinism, vector-versus-single
equivalence, and short episodes on a few seeds that must succeed. ``-m slow``: the acceptance runs (100 seeded
episodes per task, a 64-environment vector run with autoresets, Pendulum-v1 over 20 seeds, and the IPM's
one-iteration controller over the 100 seeded episodes).
"""

import dataclasses
import gc
import io

import gymnasium as gym
import numpy as np
import pytest
import torch

import torchtraj as tt
from torchtraj import envs
from torchtraj.bench import mpc as bench
from torchtraj.control.mpc import DEFAULT_ALTRO


def pendulum_mpc(iterations=2, **kwargs):
    env = envs.PendulumEnv()
    return tt.MPC(env.problem(), "altro", iterations, **kwargs), env


def step_options(iterations):
    return dataclasses.replace(DEFAULT_ALTRO, iterations_inner=iterations, iterations_outer=1)


# a swing (bound active), one near upright (bound inactive), one hanging
STATES = torch.tensor([[0.3, 2.0], [3.0, 0.2], [0.05, 0.0]], dtype=torch.float64)


# ---------------------------------------------------------------------------------------------- one control step
def test_first_control_is_the_solvers_first_control_clamped_to_the_bounds():
    mpc, _ = pendulum_mpc()
    u = mpc(STATES)
    sol = tt.solve(mpc.problem, STATES, "altro", options=step_options(2))
    torch.testing.assert_close(u, sol.U[:, 0].clamp(-3.0, 3.0), rtol=0, atol=1e-12)
    assert sol.U[:, 0].abs().max() > 3.0  # the clamp is exercised: 2 iterations leave the bound slightly violated
    assert u.abs().max() <= 3.0
    torch.testing.assert_close(mpc.U, sol.U, rtol=0, atol=1e-12)
    assert mpc.X.shape == (3, 31, 2) and mpc.status.shape == (3,)
    assert (mpc.status == tt.Status.MAX_ITERATIONS).any()  # within budget, not converged: still applied


def test_warm_start_is_the_shifted_solution_and_the_next_step_solves_from_it():
    mpc, _ = pendulum_mpc()
    mpc(STATES)
    first = mpc.solution
    assert (first.status == tt.Status.MAX_ITERATIONS).all()  # ALTRO updated every multiplier itself
    U0, duals = mpc.warm_start()
    torch.testing.assert_close(U0[:, :-1], first.U[:, 1:], rtol=0, atol=0)
    torch.testing.assert_close(U0[:, -1], first.U[:, -1], rtol=0, atol=0)
    for name, lam in first.multipliers.items():
        torch.testing.assert_close(duals["multipliers"][name][:, :-1], lam[:, 1:], rtol=0, atol=0)
    assert any(lam[:, 1:].abs().max() > 0 for lam in first.multipliers.values())  # multipliers really carried
    assert "penalties" not in duals  # penalties restart at penalty_initial (module docstring)
    x1 = first.X[:, 1]
    u = mpc(x1)
    sol = tt.solve(mpc.problem, x1, "altro", U0=U0, options=step_options(2), duals=duals)
    torch.testing.assert_close(u, sol.U[:, 0].clamp(-3.0, 3.0), rtol=0, atol=1e-12)
    cold = tt.solve(mpc.problem, x1, "altro", options=step_options(2))
    assert (sol.U - cold.U).abs().max() > 1e-3  # the warm start changes the answer


def test_a_multiple_shooting_method_starts_from_the_shifted_states(monkeypatch):
    """The IPM's warm step starts from (x̂, x_2, ..., x_N, x_N) of the previous solution, not from a rollout; ALTRO,
    whose X0 is its infeasible start, gets none."""
    import torchtraj.control.mpc as mpc_module

    given = []

    def spy(*args, **kwargs):
        given.append(kwargs.get("X0"))
        return tt.solve(*args, **kwargs)

    monkeypatch.setattr(mpc_module, "solve", spy)
    env = envs.PendulumEnv()
    ipm = tt.MPC(env.problem(), "ipm", 2)
    ipm(STATES)
    previous = ipm.solution.X
    x1 = STATES + 0.01
    ipm(x1)
    assert given[0] is None  # the first step is cold: the method's own start
    torch.testing.assert_close(given[1][:, 0], x1, rtol=0, atol=0)
    torch.testing.assert_close(given[1][:, 1:-1], previous[:, 2:], rtol=0, atol=0)
    torch.testing.assert_close(given[1][:, -1], previous[:, -1], rtol=0, atol=0)
    altro = tt.MPC(env.problem(), "altro", 2)
    altro(STATES)
    altro(x1)
    assert given[2] is None and given[3] is None


def test_the_ipms_control_steps_take_no_least_squares_multipliers(monkeypatch):
    """A control step of the IPM (its step options) takes no least-squares multiplier estimate, and so one
    factorisation fewer: its first step starts the costates at zero, the later ones from the carried duals; a solve
    with the method's defaults takes it."""
    import torchtraj.solvers.ipm.solver as ipm_solver

    estimated = []
    estimate = ipm_solver.least_squares_multipliers
    monkeypatch.setattr(ipm_solver, "least_squares_multipliers", lambda *a: estimated.append(1) or estimate(*a))
    env = envs.PendulumEnv()
    ipm = tt.MPC(env.problem(), "ipm", 2)
    ipm(STATES)
    ipm(STATES + 0.01)
    assert estimated == [] and not ipm.options.least_squares_multipliers
    tt.solve(env.problem(), STATES, method="ipm", options=tt.IPOptions(iterations=2))
    assert estimated == [1]


@pytest.mark.parametrize("method", ["ipm", "hm-ilqr", "eilqr"])
def test_a_cold_instance_among_warm_ones_starts_as_it_would_alone(method):
    """After a reset of one instance the others keep their shifted states, and the reset one starts where the
    method's own first step starts (the IPM and eILQR: the rollout of the cold controls; HM-iLQR: the line to the
    goal): its control equals a fresh controller's for it alone, and the warm ones' equal a run without that
    instance."""
    problem = tt.problems.get("pendulum")  # a goal among its parameters: HM-iLQR's line to it
    both = tt.MPC(problem, method, 2)
    both(STATES[:2])
    x1 = STATES[:2] + 0.01
    both.reset(np.array([True, False]))
    u = both(x1)
    fresh = tt.MPC(problem, method, 2)
    torch.testing.assert_close(u[0], fresh(x1[0]), rtol=0, atol=1e-12)
    warm_alone = tt.MPC(problem, method, 2)
    warm_alone(STATES[1:2])
    torch.testing.assert_close(u[1:], warm_alone(x1[1:]), rtol=0, atol=1e-12)


def test_instances_that_converge_still_get_one_multiplier_update():
    mpc, _ = pendulum_mpc(iterations=10)
    x = torch.tensor([[torch.pi + 0.05, 0.0], [torch.pi - 0.02, 0.1]], dtype=torch.float64)
    mpc(x)
    # over-estimated multipliers on bounds that are inactive near upright (as a swing-up can leave them)
    mpc._duals = {"multipliers": {k: torch.full_like(v, 0.5) for k, v in mpc.solution.multipliers.items()}}
    mpc._warm[:] = True
    mpc(x)
    sol = mpc.solution
    # ALTRO's own (fast) tolerances met: CONVERGED, or STALLED where the KKT certificate asks for more
    assert ((sol.status == tt.Status.CONVERGED) | (sol.status == tt.Status.STALLED)).all()
    _, duals = mpc.warm_start()
    for name, c in (("u_upper", sol.U - 3.0), ("u_lower", -3.0 - sol.U)):  # eq. (17) by hand, mu = 1
        expected = (0.5 + c).clamp_min(0.0)
        # a finished step reports eq. (17)'s update as its multiplier estimate, and hands it on shifted
        torch.testing.assert_close(sol.multipliers[name], expected, rtol=0, atol=1e-12)
        torch.testing.assert_close(duals["multipliers"][name][:, :-1], expected[:, 1:], rtol=0, atol=1e-12)
        assert (duals["multipliers"][name] < 0.5).all()


def test_reset_drops_the_warm_start_of_masked_instances_only():
    mpc, _ = pendulum_mpc()
    mpc(STATES)
    shifted, duals = mpc.warm_start()
    mpc.reset(np.array([False, True, False]))
    U0, after = mpc.warm_start()
    torch.testing.assert_close(U0[1], mpc.problem.u_init, rtol=0, atol=0)
    torch.testing.assert_close(U0[[0, 2]], shifted[[0, 2]], rtol=0, atol=0)
    for name, lam in after["multipliers"].items():
        assert lam[1].abs().max() == 0
        torch.testing.assert_close(lam[[0, 2]], duals["multipliers"][name][[0, 2]], rtol=0, atol=0)
    mpc.reset()
    assert torch.equal(mpc.warm_start()[0], mpc.problem.u_init.expand(3, -1, -1))
    with pytest.raises(ValueError, match="mask"):
        mpc.reset(np.array([True, False]))


def test_observation_kinds_and_unbatched_calls():
    mpc, _ = pendulum_mpc()
    out = mpc(STATES.numpy())
    assert isinstance(out, np.ndarray) and out.shape == (3, 1) and out.dtype == np.float64
    mpc.reset()
    single = mpc(STATES[0].to(torch.float32))
    assert isinstance(single, torch.Tensor) and single.shape == (1,) and single.dtype == torch.float32
    np.testing.assert_allclose(single.numpy(), out[0], rtol=1e-6, atol=1e-6)  # float32 rounding of the state


def test_a_failing_instance_changes_no_other_and_applies_its_warm_start():
    mpc, _ = pendulum_mpc()
    bad = STATES.clone()
    bad[1] = float("nan")
    u = mpc(bad)
    assert mpc.status[1] == tt.Status.NON_FINITE
    assert torch.equal(u[1], mpc.problem.u_init[0])  # cold start control, as there was no warm start
    assert not mpc._warm[1] and mpc._warm[[0, 2]].all()
    alone, _ = pendulum_mpc()
    torch.testing.assert_close(u[[0, 2]], alone(STATES[[0, 2]]), rtol=0, atol=1e-10)


def test_per_call_parameters_rebuild_the_problem_only_when_they_change():
    env = envs.CarEnv()
    mpc = bench.controller("car", env)
    obs = np.stack([env.reset(seed=s)[0] for s in (0, 1)])
    mpc(obs)
    problem = mpc.problem
    assert torch.equal(problem.params["obstacles"], torch.as_tensor(obs[:, 3:]).reshape(2, -1, 3))
    mpc(obs)
    assert mpc.problem is problem
    obs[1, 3] += 0.1
    mpc(obs)
    assert mpc.problem is not problem and mpc.problem.params["obstacles"][1, 0, 0] == obs[1, 3]


def test_ilqr_method_and_a_new_batch_size():
    mpc, _ = pendulum_mpc()
    mpc(STATES)
    u = mpc(STATES[:2])  # a new batch: every instance starts cold
    torch.testing.assert_close(u, pendulum_mpc()[0](STATES[:2]), rtol=0, atol=1e-12)
    with pytest.warns(UserWarning, match="ignores the constraints"):  # said at construction
        ilqr = tt.MPC(mpc.problem, "ilqr", 2)
    with pytest.warns(UserWarning, match="ignores the constraints"):
        u = ilqr(STATES)
        sol = tt.solve(mpc.problem, STATES, "ilqr", options=tt.ILQROptions(iterations=2))
    torch.testing.assert_close(u, sol.U[:, 0].clamp(-3.0, 3.0), rtol=0, atol=1e-12)
    assert sol.U[:, 0].abs().max() > 3.0 and ilqr.warm_start()[1] is None  # clamped; no multipliers to carry


def test_construction_errors_name_the_argument():
    problem = envs.PendulumEnv().problem()
    with pytest.raises(ValueError, match="method"):
        tt.MPC(problem, "newton")
    with pytest.raises(ValueError, match="iterations"):
        tt.MPC(problem, iterations=0)
    with pytest.raises(TypeError, match="IPOptions"):  # the default method's
        tt.MPC(problem, options=tt.ILQROptions())
    with pytest.raises(TypeError, match="ALTROOptions"):
        tt.MPC(problem, "altro", options=tt.ILQROptions())
    with pytest.raises(TypeError, match="Problem"):
        tt.MPC("pendulum")
    with pytest.raises(ValueError, match="observation_to_state"):
        tt.MPC(problem)(np.zeros((2, 3)))


# ---------------------------------------------------------------------------------------------- vector environments
class Recorder:
    """Wraps a policy and keeps every batch of observations and actions it saw."""

    def __init__(self, policy):
        self.policy, self.calls = policy, []

    def __call__(self, obs):
        actions = self.policy(obs)
        self.calls.append((np.array(obs), np.array(actions)))
        return actions

    def reset(self, mask=None):
        self.policy.reset(mask)


def test_autoreset_drops_the_warm_start_of_restarted_episodes_only():
    venv = gym.make_vec("torchtraj/Pendulum-v0", num_envs=3, max_episode_steps=4)
    mpc = Recorder(bench.controller("pendulum", venv, iterations=2))
    run = bench.run_episodes(venv, mpc, episodes_per_env=2, seed=3)
    assert len(run.episodes) == 6 and all(len(e.rewards) == 4 for e in run.episodes)
    # calls 0-3 play the first episodes, call 4 the ignored autoreset step, call 5 the second episodes' first step
    obs, actions = mpc.calls[5]
    second = sorted(run.episodes[3:], key=lambda e: e.env)  # every first episode ends at the same step
    np.testing.assert_array_equal(obs, np.stack([e.observations[0] for e in second]))
    cold = bench.controller("pendulum", venv, iterations=2)(obs)
    np.testing.assert_allclose(actions, cold, rtol=0, atol=1e-9)  # a fresh start for every restarted instance
    obs6, actions6 = mpc.calls[6]
    assert np.abs(actions6 - bench.controller("pendulum", venv, iterations=2)(obs6)).max() > 1e-6  # then warm


def _play(env_or_venv, mpc, seed, steps):
    obs, _ = env_or_venv.reset(seed=seed)
    actions = []
    for _ in range(steps):
        action = mpc(obs)
        actions.append(action)
        obs, *_ = env_or_venv.step(action)
    return np.stack(actions)


def test_seeded_episodes_are_deterministic():
    runs = [_play(envs.PendulumEnv(), pendulum_mpc()[0], 7, 6) for _ in range(2)]
    np.testing.assert_array_equal(runs[0], runs[1])
    assert not np.allclose(runs[0], _play(envs.PendulumEnv(), pendulum_mpc()[0], 8, 6))


def test_vector_environment_and_batched_mpc_match_single_ones():
    venv = gym.make_vec("torchtraj/Pendulum-v0", num_envs=3)
    batched = _play(venv, bench.controller("pendulum", venv, iterations=2), 11, 6)  # (steps, 3, 1)
    for i in range(3):
        env = envs.PendulumEnv()
        single = _play(env, bench.controller("pendulum", env, iterations=2), 11 + i, 6)
        np.testing.assert_allclose(batched[:, i], single, rtol=0, atol=1e-9)


# ---------------------------------------------------------------------------------------------- short episodes
@pytest.mark.parametrize("method", ["ipm", "altro"])  # the default controller, and the one it replaced
def test_pendulum_swings_up_and_stays_up(method):
    venv = gym.make_vec("torchtraj/Pendulum-v0", num_envs=2, max_episode_steps=80)
    run = bench.run_episodes(venv, bench.controller("pendulum", venv, method=method), seed=0)
    for episode in run.episodes:  # from hanging (|e| = π) to within 0.1 rad of upright over the last 0.75 s
        error = bench.upright_error(torch.as_tensor(episode.observations[:, 0])).abs()
        assert error[0] > 3.0 and (error[-16:] <= 0.1).all()  # seeds 0, 1 up from steps 41, 42 (ALTRO: 58, 46)


@pytest.mark.slow  # a minute of the default run; the same path is tested on shorter problems
def test_cartpole_swings_up_without_leaving_the_rail():
    venv = gym.make_vec("torchtraj/CartPoleSwingUp-v0", num_envs=2, max_episode_steps=115)
    run = bench.run_episodes(venv, bench.controller("cartpole", venv), seed=0)
    for episode in run.episodes:  # truncated, not terminated: the cart stayed on the rail
        error = bench.upright_error(torch.as_tensor(episode.observations[:, 1])).abs()
        assert not episode.terminated and error[0] > 3.0 and (error[-10:] <= 0.1).all()  # up from steps 98, 85


@pytest.mark.slow  # a 3-obstacle car episode; the pendulum episodes stay in the default run
def test_car_reaches_the_goal_without_collision():
    venv = gym.make_vec("torchtraj/Car-v0", num_envs=2)
    run = bench.run_episodes(venv, bench.controller("car", venv), seed=1)  # seed 1: an obstacle right ahead
    assert [bench.car_success(e) for e in run.episodes] == [True, True]


def test_pendulum_v1_model_is_gymnasiums_step():
    example = bench.pendulum_v1_example()
    env = gym.make("Pendulum-v1").unwrapped
    rng = np.random.default_rng(0)
    for _ in range(50):  # speeds up to 9 > 8 and torques beyond 2 reach the clips
        x, u = rng.uniform([-4, -9], [4, 9]), rng.uniform(-2.5, 2.5, 1)
        env.reset(seed=0)
        env.state = x.copy()
        env.step(u.astype(np.float32))
        ours = example.pendulum_v1_step(torch.as_tensor(x), torch.as_tensor(u).clamp(-2, 2), example.PARAMS)
        np.testing.assert_allclose(ours.numpy(), env.state, rtol=0, atol=1e-6)  # float32 action rounding


def test_bench_mpc_flag_prints_the_timing_rows():
    from torchtraj.bench.__main__ import main

    out = io.StringIO()
    code = main(["--mpc", "--tasks", "pendulum", "--episodes", "0", "--vector-envs", "0", "--timing-batch", "1", "2",
                 "--timing-steps", "2"], out=out)
    rows = [line for line in out.getvalue().splitlines() if line.startswith("B=")]
    assert code == 0 and len(rows) == 2 and all("horizon 30, 3 iterations/step" in r and "expansion" in r for r in rows)


def test_full_collections_counts_the_garbage_collector_s_full_passes_alone():
    with bench.FullCollections() as seen:
        gc.collect(0)
        gc.collect(1)
        assert seen.count == 0
        gc.collect()
        assert seen.count == 1
    gc.collect()
    assert seen.count == 1 and seen._seen not in gc.callbacks


def test_bench_mpc_timing_reports_the_slowest_step_and_freezes_for_the_timed_steps_alone():
    from torchtraj.bench.__main__ import main

    out = io.StringIO()
    main(["--mpc", "--tasks", "pendulum", "--episodes", "0", "--vector-envs", "0", "--v1-seeds", "0",
          "--timing-batch", "1", "--timing-steps", "2", "--freeze-gc"], out=out)
    row = next(line for line in out.getvalue().splitlines() if line.startswith("B=1"))
    assert "ms max per step (" in row and "full garbage collections, objects frozen)" in row
    assert gc.get_freeze_count() == 0  # unfrozen after the profiled steps


def test_bench_mpc_runs_another_method_at_another_iteration_budget():
    from torchtraj.bench.__main__ import main

    env = gym.make(bench.IDS["pendulum"])
    mpc = bench.controller("pendulum", env, iterations=1, method="ipm")
    assert mpc.method == "ipm" and mpc.options.iterations == 1
    with pytest.raises(ValueError, match="ALTRO's"):
        bench.controller("pendulum", env, method="ipm", penalty_initial=10.0)
    out = io.StringIO()
    main(["--mpc", "--tasks", "pendulum", "--episodes", "1", "--vector-envs", "0", "--timing-batch", "1",
          "--timing-steps", "2", "--method", "ipm", "--iterations", "1"], out=out)
    lines = out.getvalue().splitlines()
    assert "controllers: method ipm, 1 iterations per control step" in lines
    episodes = next(line for line in lines if line.startswith("pendulum")).split()
    timing = next(line for line in lines if line.startswith("B=1"))
    assert episodes[-5] == "1" and "horizon 30, 1 iterations/step" in timing
    with pytest.raises(SystemExit):
        main(["--mpc", "--iterations", "0"], out=io.StringIO())


# ---------------------------------------------------------------------------------------------- acceptance (slow)
@pytest.mark.slow
@pytest.mark.parametrize("task", ["pendulum", "cartpole", "car"])
def test_acceptance_100_seeded_episodes(task):
    run = bench.acceptance(task, num_envs=100, episodes_per_env=1, seed=0)
    rate = run.rate(bench.SUCCESS[task])
    print(f"{task}: success rate {rate:.2f} over {len(run.episodes)} seeded episodes")
    assert len(run.episodes) == 100 and rate >= 0.95


@pytest.mark.slow
@pytest.mark.parametrize("task", ["pendulum", "cartpole", "car"])
def test_acceptance_64_env_vector_run_with_autoresets(task):
    run = bench.acceptance(task, num_envs=64, episodes_per_env=2, seed=10_000)
    rate = run.rate(bench.SUCCESS[task])
    print(f"{task}: success rate {rate:.2f} over {len(run.episodes)} episodes of a 64-environment vector run")
    assert len(run.episodes) == 128 and rate >= 0.95


@pytest.mark.slow
def test_acceptance_gymnasium_pendulum_v1():
    example = bench.pendulum_v1_example()
    returns, theta, _ = example.run(seeds=20, seed=0)
    upright = example.wrap(theta[:, -1]).abs() <= 0.1
    print(f"Pendulum-v1: average return {returns.mean():.1f} over 20 seeds, ended upright {int(upright.sum())}/20")
    assert returns.mean() > -200 and upright.all()


@pytest.mark.slow
@pytest.mark.parametrize("task", ["pendulum", "cartpole", "car"])
def test_acceptance_of_the_ipms_one_iteration_controller(task):
    """One interior-point iteration a step, warm-started from the last step's duals (measured: 100, 100 and 99 of
    100; cold, before the warm start: 100, 84 and 78)."""
    run = bench.acceptance(task, num_envs=100, episodes_per_env=1, seed=0, method="ipm", iterations=1)
    rate = run.rate(bench.SUCCESS[task])
    print(f"{task}: the IPM at one iteration a step, success rate {rate:.2f} over {len(run.episodes)} episodes")
    assert len(run.episodes) == 100 and rate >= 0.95
