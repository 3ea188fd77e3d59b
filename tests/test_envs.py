"""The torchtraj.envs package: Gymnasium API, seeding, dynamics identity with torchtraj.models, vector/single
equivalence, registration by ``import torchtraj``, and the package's name once installed."""

import os
import re
import shutil
import subprocess
import sys
import warnings
import zipfile
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode, SyncVectorEnv

from torchtraj import envs, models

DT = 0.05
MODEL_OF = {"torchtraj/Pendulum-v0": "pendulum", "torchtraj/CartPoleSwingUp-v0": "cartpole",
            "torchtraj/Car-v0": "unicycle"}
CLASS_OF = {"torchtraj/Pendulum-v0": (envs.PendulumEnv, envs.PendulumVectorEnv),
            "torchtraj/CartPoleSwingUp-v0": (envs.CartPoleSwingUpEnv, envs.CartPoleSwingUpVectorEnv),
            "torchtraj/Car-v0": (envs.CarEnv, envs.CarVectorEnv)}
# the only warnings check_env may give: our observations are unbounded and our actions physical, not normalised
EXPECTED_WARNINGS = re.compile("Box observation space (minimum|maximum) value is -?infinity|"
                               "recommend using a symmetric and normalized space")


@pytest.mark.parametrize("env_id", envs.IDS)
def test_check_env_passes_with_only_the_expected_warnings(env_id):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(gym.make(env_id).unwrapped)
    unexpected = [str(w.message) for w in caught if not EXPECTED_WARNINGS.search(str(w.message))]
    assert unexpected == []


@pytest.mark.parametrize("env_id", envs.IDS)
def test_make_and_make_vec_give_our_classes(env_id):
    single, vector = CLASS_OF[env_id]
    env = gym.make(env_id)
    assert isinstance(env.unwrapped, single) and env.spec.max_episode_steps == env.unwrapped.max_episode_steps == 200
    obs, info = env.reset(seed=0)
    assert obs.shape == env.observation_space.shape and obs.dtype == np.float64
    assert len(env.step(env.action_space.sample())) == 5
    venv = gym.make_vec(env_id, num_envs=3)
    assert type(venv) is vector and venv.num_envs == 3 and venv.max_episode_steps == 200
    assert venv.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    obs, _ = venv.reset(seed=0)
    assert obs.shape == (3, *env.observation_space.shape) and obs in venv.observation_space
    assert isinstance(gym.make_vec(env_id, num_envs=2, vectorization_mode="sync"), SyncVectorEnv)


def test_episodes_truncate_inside_the_environment():
    env = envs.PendulumEnv()  # no TimeLimit wrapper: the limit is the environment's own
    env.reset(seed=0)
    truncated = [env.step(np.zeros(1))[3] for _ in range(200)]
    assert truncated == [False] * 199 + [True]


def _rollout(env, seed, actions):
    obs = [env.reset(seed=seed)[0]]
    for a in actions:
        out = env.step(a)
        obs.append(out[0])
        if out[2] or out[3]:
            break
    return np.stack(obs)


@pytest.mark.parametrize("env_id", envs.IDS)
def test_seeded_determinism(env_id):
    env = gym.make(env_id)
    low, high = env.action_space.low, env.action_space.high
    actions = np.random.default_rng(1).uniform(low, high, (30, low.shape[0]))
    first, again, other = _rollout(env, 5, actions), _rollout(env, 5, actions), _rollout(env, 6, actions)
    np.testing.assert_array_equal(first, again)
    assert first.shape != other.shape or not np.allclose(first, other)


# short episodes, and settings that make random actions end some episodes by termination too
VECTOR_CASES = {
    "torchtraj/Pendulum-v0": dict(max_episode_steps=9),
    "torchtraj/CartPoleSwingUp-v0": dict(max_episode_steps=15, rail_limit=0.1),
    "torchtraj/Car-v0": dict(max_episode_steps=12, goal_radius=3.5),
}


def _actions(space, rng, steps, num_envs):
    # beyond the bounds on purpose: the clipping must agree too
    low, high = space.low, space.high
    span = high - low
    return rng.uniform(low - 0.3 * span, high + 0.3 * span, (steps, num_envs, low.shape[0]))


def _single_next_step_autoreset(env_id, kwargs, seed, actions):
    """B single environments seeded seed + i, autoreset by hand as Gymnasium's NEXT_STEP mode does."""
    num_envs = actions.shape[1]
    singles = [CLASS_OF[env_id][0](**kwargs) for _ in range(num_envs)]
    obs = [np.stack([e.reset(seed=seed + i)[0] for i, e in enumerate(singles)])]
    ended = [False] * num_envs
    rewards, terms, truncs = [], [], []
    for a in actions:
        rows = []
        for i, env in enumerate(singles):
            rows.append((env.reset()[0], 0.0, False, False) if ended[i] else env.step(a[i])[:4])
        ended = [r[2] or r[3] for r in rows]
        obs.append(np.stack([r[0] for r in rows]))
        rewards.append([r[1] for r in rows]), terms.append([r[2] for r in rows]), truncs.append([r[3] for r in rows])
    return np.stack(obs), np.array(rewards), np.array(terms), np.array(truncs)


def _vector_rollout(venv, seed, actions):
    obs = [venv.reset(seed=seed)[0]]
    rewards, terms, truncs = [], [], []
    for a in actions:
        o, r, term, trunc, _ = venv.step(a)
        obs.append(o), rewards.append(r), terms.append(term), truncs.append(trunc)
    return np.stack(obs), np.array(rewards), np.array(terms), np.array(truncs)


@pytest.mark.parametrize("env_id", envs.IDS)
def test_vector_env_matches_single_envs_with_next_step_autoreset(env_id):
    kwargs, seed = VECTOR_CASES[env_id], 11
    venv = gym.make_vec(env_id, num_envs=4, **kwargs)
    assert isinstance(venv, CLASS_OF[env_id][1])
    actions = _actions(venv.single_action_space, np.random.default_rng(0), 40, 4)
    got = _vector_rollout(venv, seed, actions)
    by_hand = _single_next_step_autoreset(env_id, kwargs, seed, actions)
    sync = _vector_rollout(gym.make_vec(env_id, num_envs=4, vectorization_mode="sync", **kwargs), seed, actions)
    for reference in (by_hand, sync):
        for a, b in zip(got, reference):
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
    _, _, terminated, truncated = got
    assert truncated.any(), "the test must cross a truncation"
    assert terminated.any() == (env_id != "torchtraj/Pendulum-v0"), "and a termination where the task has one"


@pytest.mark.parametrize("env_id", envs.IDS)
def test_dynamics_are_the_torchtraj_model(env_id):
    env = gym.make(env_id).unwrapped
    model = models.get(MODEL_OF[env_id])
    assert env.model.dynamics is model.dynamics and env.dt == DT  # the model's own function, not a copy
    step = model.discrete(DT, "rk4")
    obs, _ = env.reset(seed=3)
    rng = np.random.default_rng(3)
    for _ in range(5):
        x = torch.as_tensor(env.observation_to_state(obs))
        np.testing.assert_array_equal(x.numpy(), env.state.numpy())
        u = rng.uniform(env.action_space.low, env.action_space.high)
        obs = env.step(u)[0]
        expected = step(x, torch.as_tensor(u), model.params)
        torch.testing.assert_close(torch.as_tensor(env.observation_to_state(obs)), expected, rtol=0, atol=1e-12)
    venv = gym.make_vec(env_id, num_envs=3)
    venv.reset(seed=3)
    X = venv.state
    U = torch.as_tensor(rng.uniform(env.action_space.low, env.action_space.high, (3, model.nu)))
    venv.step(U.numpy())
    expected = torch.stack([step(X[i], U[i], model.params) for i in range(3)])
    torch.testing.assert_close(venv.state, expected, rtol=0, atol=1e-12)


MODULE_OF = {"torchtraj/Pendulum-v0": envs.pendulum, "torchtraj/CartPoleSwingUp-v0": envs.cartpole,
             "torchtraj/Car-v0": envs.car}


@pytest.mark.parametrize("env_id", envs.IDS)
def test_controller_problem_is_built_on_the_environments_own_functions(env_id):
    env, module = gym.make(env_id).unwrapped, MODULE_OF[env_id]
    problem = env.problem(horizon=7)
    assert problem.N == 7 and problem.dt == env.dt and problem.dynamics is module.dynamics
    np.testing.assert_array_equal(problem.u_lower.numpy(), env.action_space.low)
    np.testing.assert_array_equal(problem.u_upper.numpy(), env.action_space.high)
    venv = gym.make_vec(env_id, num_envs=2)
    assert venv.params == env.params and venv.problem(horizon=7).params.keys() == problem.params.keys()
    obs, _ = env.reset(seed=2)
    rng = np.random.default_rng(2)
    layout = {"obstacles": env.obstacles} if env_id == "torchtraj/Car-v0" else {}
    for _ in range(10):
        x = env.state
        u = torch.as_tensor(rng.uniform(env.action_space.low, env.action_space.high))
        obs, reward, terminated, _, _ = env.step(u.numpy())
        x_next = problem.dynamics(x, u, problem.params)  # the controller's prediction, exactly the step taken
        assert torch.equal(x_next, env.state)
        assert float(module.reward(x, u, x_next, layout, env.params)) == reward  # the reward the env pays
        if env_id == "torchtraj/Pendulum-v0":  # the controller's stage cost is that reward, negated, over dt
            assert float(problem.stage_cost(x, u, problem.params)) == -env.dt * reward
        if terminated:
            break
    with pytest.raises(TypeError, match="params"):
        module.problem(envs.PendulumParams() if env_id != "torchtraj/Pendulum-v0" else envs.CarParams())


@pytest.mark.parametrize("env_id", envs.IDS)
def test_render_draws_the_state(env_id):
    env = gym.make(env_id, render_mode="rgb_array")
    env.reset(seed=0)
    first = env.render()
    assert first.dtype == np.uint8 and first.ndim == 3 and first.shape[2] == 3
    assert len(np.unique(first.reshape(-1, 3), axis=0)) >= 4  # background and at least three drawn colours
    for _ in range(10):
        env.step(env.action_space.high)
    assert not np.array_equal(env.render(), first)
    venv = gym.make_vec(env_id, num_envs=2, render_mode="rgb_array")
    venv.reset(seed=0)
    frames = venv.render()
    assert len(frames) == 2 and np.array_equal(frames[0], first)


def test_car_layout_depends_on_the_seed_and_leaves_start_and_goal_free():
    env = envs.CarEnv()
    layouts = []
    for seed in range(100):
        obs, _ = env.reset(seed=seed)
        circles, goal = env.obstacles.numpy(), env.goal.numpy()
        assert circles.shape == (4, 3)
        np.testing.assert_array_equal(env.observation_to_obstacles(obs), circles)
        centres, radii = circles[:, :2], circles[:, 2]
        assert (np.linalg.norm(centres - obs[:2], axis=1) > radii).all()
        assert (np.linalg.norm(centres - goal, axis=1) > radii + env.goal_radius).all()
        gaps = np.linalg.norm(centres[:, None] - centres[None], axis=-1) - radii[:, None] - radii[None]
        assert (gaps[~np.eye(4, dtype=bool)] >= 0.3).all()
        layouts.append(circles)
    env.reset(seed=0)
    np.testing.assert_array_equal(env.obstacles.numpy(), layouts[0])
    assert len({a.tobytes() for a in layouts}) == 100


def test_car_ends_on_collision_and_on_reaching_the_goal():
    env = envs.CarEnv()
    env.reset(seed=0)
    cx, cy, r = env.obstacles[0].tolist()
    # heading at the first obstacle from just outside it: one full-speed step goes in
    env.reset(seed=0, options={"state": [cx - r - 0.05, cy, 0.0]})
    _, reward, terminated, truncated, info = env.step(np.array([3.0, 0.0]))
    assert terminated and not truncated and info == {"collided": True, "reached_goal": False} and reward < -9.0
    gx, gy = env.goal.tolist()
    env.reset(seed=0, options={"state": [gx - 0.3, gy, 0.0]})
    _, reward, terminated, _, info = env.step(np.array([3.0, 0.0]))
    assert terminated and info == {"collided": False, "reached_goal": True} and reward > 10.0


def test_cartpole_ends_off_the_rail():
    env = envs.CartPoleSwingUpEnv()
    env.reset(seed=0, options={"state": [2.39, 0.0, 1.0, 0.0]})
    _, reward, terminated, _, _ = env.step(np.array([3.0]))
    assert terminated and 0.0 <= reward <= 1.0


@pytest.mark.parametrize("env_id", envs.IDS)
def test_out_of_bounds_actions_are_clipped_and_nan_raises(env_id):
    env = gym.make(env_id).unwrapped
    low, high = env.action_space.low, env.action_space.high
    results = []
    for action in (high + 10.0, high, np.full_like(high, np.inf)):
        env.reset(seed=0)
        results.append(env.step(action)[0])
    np.testing.assert_array_equal(results[0], results[1])
    np.testing.assert_array_equal(results[2], results[1])
    with pytest.raises(ValueError, match="NaN"):
        env.step(np.full_like(low, np.nan))
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(low.shape[0] + 1))
    venv = gym.make_vec(env_id, num_envs=2)
    venv.reset(seed=0)
    with pytest.raises(ValueError, match="NaN"):
        venv.step(np.stack([high, np.full_like(low, np.nan)]))


def test_vector_env_resets_by_mask_seeds_by_list_and_returns_tensors():
    venv = envs.PendulumVectorEnv(3, array_type="torch")
    obs, _ = venv.reset(seed=[4, 5, 6])
    assert isinstance(obs, torch.Tensor) and obs.dtype == torch.float64
    np.testing.assert_array_equal(obs[1].numpy(), envs.PendulumEnv().reset(seed=5)[0])
    moved = venv.step(torch.ones(3, 1))[0]
    obs, _ = venv.reset(seed=[None, 9, None], options={"reset_mask": np.array([False, True, False])})
    np.testing.assert_array_equal(obs[[0, 2]].numpy(), moved[[0, 2]].numpy())
    np.testing.assert_array_equal(obs[1].numpy(), envs.PendulumEnv().reset(seed=9)[0])
    assert venv.elapsed_steps.tolist() == [1, 0, 1]
    x0 = torch.tensor([np.pi, 0.0], dtype=torch.float64)
    obs, _ = venv.reset(options={"state": x0})
    assert torch.equal(obs, x0.expand(3, 2))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("env_id", envs.IDS)
def test_vector_env_on_cuda_matches_cpu(env_id):
    kwargs = VECTOR_CASES[env_id]
    actions = _actions(gym.make(env_id).action_space, np.random.default_rng(0), 40, 8)
    cpu = _vector_rollout(gym.make_vec(env_id, num_envs=8, **kwargs), 2, actions)
    cuda = _vector_rollout(gym.make_vec(env_id, num_envs=8, device="cuda", **kwargs), 2, actions)
    for a, b in zip(cpu, cuda):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)


# ---------------------------------------------------------------------------------------------- name and registration
ROOT = Path(__file__).resolve().parent.parent


def _python(code: str, cwd: Path) -> str:
    """Run ``code`` in a fresh interpreter that imports this checkout (``PYTHONPATH``) from ``cwd``."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, "-c", code], cwd=cwd, env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return done.stdout


def test_import_torchtraj_registers_the_ids_without_importing_the_environments(tmp_path):
    out = _python("import sys, gymnasium, torchtraj\n"
                  "print('torchtraj.envs' in sys.modules)\n"
                  "env = gymnasium.make('torchtraj/Pendulum-v0')\n"
                  "print(type(env.unwrapped).__module__, env.unwrapped.problem().name)\n", tmp_path)
    assert out.split() == ["False", "torchtraj.envs.pendulum", "pendulum_mpc"]


def test_make_vec_returns_torch_tensors_when_asked():
    venv = gym.make_vec("torchtraj/Car-v0", num_envs=2, array_type="torch")
    obs, _ = venv.reset(seed=0)
    obs, reward, terminated, truncated, _ = venv.step(torch.zeros(2, 2))
    assert all(isinstance(a, torch.Tensor) for a in (obs, reward, terminated, truncated))
    assert isinstance(gym.make_vec("torchtraj/Car-v0", num_envs=2).reset(seed=0)[0], np.ndarray)


@pytest.mark.slow
def test_the_wheel_installs_torchtraj_envs_and_no_top_level_envs(tmp_path):
    """The packaging maps ``envs/`` to ``torchtraj.envs``: the wheel holds the environments under torchtraj/ and
    nothing named ``envs`` at its top (the installs by hand: torchtraj/envs/__init__.py)."""
    source = tmp_path / "source"  # a copy: building writes build/ and egg-info next to the sources
    for part in ("envs", "torchtraj"):
        shutil.copytree(ROOT / part, source / part, ignore=shutil.ignore_patterns("__pycache__"))
    for part in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / part, source / part)
    done = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-w",
                           str(tmp_path), str(source)], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    (wheel,) = tmp_path.glob("torchtraj-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names}
    assert tops == {"torchtraj", next(t for t in tops if t.endswith(".dist-info"))}
    for module in ("__init__", "core", "vector", "pendulum", "cartpole", "car", "render"):
        assert f"torchtraj/envs/{module}.py" in names
    shipped = zipfile.ZipFile(wheel).read("torchtraj/envs/__init__.py").decode()
    assert shipped == (ROOT / "envs" / "__init__.py").read_text()  # the package itself, not the checkout's shim
