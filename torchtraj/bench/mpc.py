r"""MPC on the torchtraj environments: the controllers, their acceptance runs and their timing.

``python -m torchtraj.bench --mpc`` prints, for every task, the success rate over seeded episodes (episode ``i``
of a run seeded ``s`` is the single environment seeded ``s + i``; a vector environment of B sub-environments plays
them with one batched :class:`~torchtraj.MPC` call per step), and the time per control step at B = 1 and B = 64.

Controllers (:func:`controller`): each environment's own problem, ``env.problem(...)`` (see the
"Controller Problem" section of the environment's docstring: the pendulum's cost is its reward, negated; the
cart-pole's and the car's are quadratics with the reward's optimum, the car's obstacles constraints), on the step
the environment takes, solved by :class:`~torchtraj.MPC`'s default, the interior point (at most 3 iterations a step;
``--method``, ``--iterations`` choose others), warm-started from the previous step's shifted solution::

    pendulum  N = 30 (1.5 s),  |τ| ≤ 3
    cartpole  N = 40 (2 s),    |F| ≤ 3,   |x| ≤ 2 (the rail ends at 2.4)
    car       N = 30 (1.5 s),  0 ≤ v ≤ 3,   |ω| ≤ 3,   ‖p − c_i‖ ≥ r_i + 0.15 for each observed obstacle

ALTRO's car penalties start at ``penalty_initial = 100`` (:data:`TASK_OPTIONS`): with ALTRO's default of 1, 17 of
64 seeds drive into an obstacle right ahead in the first steps from a cold start, before the multipliers have grown.

Success of an episode (200 steps, 10 s):

    pendulum  |wrap(θ − π)| ≤ 0.1 at every step of the second half (from 5 s on): upright, and kept there;
    cartpole  never left the rail (not terminated) and |wrap(θ − π)| ≤ 0.1 at every step of the last 2.5 s;
    car       reached the goal (terminated with ``reached_goal``) without a collision.
"""

from __future__ import annotations

import dataclasses
import gc
import time
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np
import torch

from torchtraj.envs.core import upright_error  # importing torchtraj registers the environments

from .. import solvers
from ..control.mpc import DEFAULT_ALTRO, MPC
from ..core.progress import Progress
from ..core.recorded import TRACE_AT
from . import profile

IDS = {"pendulum": "torchtraj/Pendulum-v0", "cartpole": "torchtraj/CartPoleSwingUp-v0", "car": "torchtraj/Car-v0"}

#: ALTRO options of each task's controller, on top of :data:`torchtraj.control.mpc.DEFAULT_ALTRO`.
TASK_OPTIONS = {"pendulum": {}, "cartpole": {}, "car": {"penalty_initial": 100.0}}


def controller(task: str, env, horizon: Optional[int] = None, iterations: int = 3, problem_options=None,
               compile: bool = False, method: str = "ipm", **options) -> MPC:
    """The :class:`~torchtraj.MPC` of ``task`` (``"pendulum"``, ``"cartpole"``, ``"car"``) for ``env``, a single or
    vector environment of that task; ``problem_options`` go to the environment's own problem builder,
    ``env.problem(**problem_options)``, ``compile`` to the policy. ``method``: one that handles constraints, with its
    control-step options; for ``"altro"``, ``options`` are :class:`~torchtraj.ALTROOptions` fields to change from
    :data:`TASK_OPTIONS` (another method takes none)."""
    if task not in IDS:
        raise ValueError(f"unknown task {task!r}; known tasks are {sorted(IDS)}")
    problem_options = dict(problem_options or {})
    if horizon is not None:
        problem_options["horizon"] = horizon
    problem = env.unwrapped.problem(**problem_options)  # gymnasium.make wraps
    if method == "altro":
        opts = dataclasses.replace(DEFAULT_ALTRO, **{**TASK_OPTIONS[task], **options})
    elif options:
        raise ValueError(f"options {sorted(options)} are ALTRO's; method {method!r} takes its own step options")
    else:
        opts = None
    if task != "car":
        return MPC(problem, method, iterations, opts, compile=compile)
    n = problem.params["obstacles"].shape[0]
    return MPC(problem, method, iterations, opts, observation_to_state=lambda obs: obs[:, :3],
               observation_to_params=lambda obs: {"obstacles": obs[:, 3:].reshape(obs.shape[0], n, 3)},
               compile=compile)


# ---------------------------------------------------------------------------------------------- episodes
@dataclass
class Episode:
    """One finished episode of sub-environment ``env``: observations ``(T+1, n_obs)`` (first to final), rewards
    ``(T,)``, per-step ``info`` entries ``{name: (T,)}``, how it ended, and the actions ``(T, nu)`` it took (as the
    policy returned them; the environment clips them to its action space)."""

    env: int
    observations: np.ndarray
    rewards: np.ndarray
    infos: dict
    terminated: bool
    actions: Optional[np.ndarray] = None

    @property
    def total(self) -> float:
        return float(self.rewards.sum())


@dataclass
class Run:
    """Episodes of a vector run, the seconds of each batched policy call, and the policy's last solver status."""

    episodes: list
    step_seconds: list

    def rate(self, success: Callable[[Episode], bool]) -> float:
        return float(np.mean([success(e) for e in self.episodes]))


def run_episodes(venv, policy, episodes_per_env: int = 1, seed: int = 0, on_step: Optional[Callable] = None,
                 progress: bool = False, label: str = "episodes") -> Run:
    """Play ``episodes_per_env`` episodes on each sub-environment of ``venv`` (next-step autoreset), calling
    ``policy`` once per step on the whole batch of observations and ``policy.reset(mask)`` with the
    sub-environments that just restarted. Sub-environments that are done wait (their extra episodes are dropped).
    ``progress`` draws a bar on stderr (:class:`~torchtraj.core.progress.Progress`): episodes finished, and the
    last control step's iterations (the batch's mean) and its plans' largest violation."""
    B = venv.num_envs
    bar = Progress(B * episodes_per_env, label, unit="episodes", enabled=progress)
    obs, _ = venv.reset(seed=seed)
    history, rewards, infos, taken = [np.asarray(obs)], [np.zeros(B)], [{}], [None]
    start, count = np.zeros(B, dtype=int), np.zeros(B, dtype=int)
    restarted = np.zeros(B, dtype=bool)
    episodes, seconds = [], []
    while (count < episodes_per_env).any():
        tick = time.perf_counter()
        actions = policy(obs)
        seconds.append(time.perf_counter() - tick)
        obs, reward, terminated, truncated, info = venv.step(actions)
        if hasattr(policy, "reset"):
            policy.reset(restarted)
        history.append(np.asarray(obs))
        taken.append(np.asarray(actions, dtype=np.float64).reshape(B, -1))
        rewards.append(np.asarray(reward, dtype=np.float64))
        infos.append({k: np.asarray(v) for k, v in info.items() if not k.startswith("_")})
        if on_step is not None:
            on_step(len(history) - 1)
        t = len(history) - 1
        start = np.where(restarted, t, start)
        done = (np.asarray(terminated) | np.asarray(truncated)) & ~restarted
        for i in np.flatnonzero(done & (count < episodes_per_env)):
            a = start[i]
            episodes.append(Episode(
                env=int(i), observations=np.stack([h[i] for h in history[a:t + 1]]),
                rewards=np.array([r[i] for r in rewards[a + 1:t + 1]]),
                infos={k: np.array([inf[k][i] for inf in infos[a + 1:t + 1]]) for k in infos[t]},
                terminated=bool(np.asarray(terminated)[i]), actions=np.stack([u[i] for u in taken[a + 1:t + 1]])))
        finished = int((done & (count < episodes_per_env)).sum())
        count = count + done
        restarted = done
        solution = getattr(policy, "solution", None)
        if solution is not None and bar.enabled:
            bar.update(finished, violation=solution.max_violation,
                       **{"iterations a step": float(solution.iterations.double().mean())})
        else:
            bar.update(finished)
    bar.close()
    return Run(episodes, seconds)


# ---------------------------------------------------------------------------------------------- success
def pendulum_success(episode: Episode, tolerance: float = 0.1) -> bool:
    """Upright (``|wrap(θ − π)| ≤ tolerance``) at every step of the episode's second half."""
    theta = torch.as_tensor(episode.observations[:, 0])
    half = len(theta) // 2
    return bool((upright_error(theta[half:]).abs() <= tolerance).all())


def cartpole_success(episode: Episode, tolerance: float = 0.1, hold_steps: int = 50) -> bool:
    """Never left the rail, and upright at every step of the last ``hold_steps`` steps (2.5 s)."""
    theta = torch.as_tensor(episode.observations[-hold_steps:, 1])
    return not episode.terminated and bool((upright_error(theta).abs() <= tolerance).all())


def car_success(episode: Episode) -> bool:
    """Reached the goal without touching an obstacle."""
    return bool(episode.infos["reached_goal"].any()) and not bool(episode.infos["collided"].any())


SUCCESS = {"pendulum": pendulum_success, "cartpole": cartpole_success, "car": car_success}


# ---------------------------------------------------------------------------------------------- timing
@dataclass
class Timing:
    """Per-control-step time of ``steps`` batched calls after the warm-up; ``parts``: :func:`profile.parts_of`'s."""

    task: str
    batch: int
    horizon: int
    iterations: int
    steps: int
    ms_median: float
    ms_mean: float
    iterations_mean: float
    parts: dict  # shares of profile.parts_of(method, compiled)
    compiled: bool = False
    warm_up_s: float = float("nan")  # the untimed warm-up steps: traces of records, torch.compile's compilation
    ms_max: float = float("nan")  # the slowest timed step
    full_collections: int = 0  # Python's full garbage collections during the timed steps (FullCollections)
    frozen: bool = False  # the objects made before the timed steps were frozen (gc.freeze)


class FullCollections:
    """Counts the full (generation 2) collections of Python's garbage collector while it is entered: each walks
    every object it tracks, some 300,000 with torch imported (``docs/benchmarks.md``, "MPC")."""

    def __enter__(self) -> "FullCollections":
        self.count = 0
        gc.callbacks.append(self._seen)
        return self

    def _seen(self, phase: str, info: dict) -> None:
        if phase == "start" and info["generation"] == 2:
            self.count += 1

    def __exit__(self, *exc) -> None:
        gc.callbacks.remove(self._seen)


def time_steps(task: str = "pendulum", batch: int = 1, steps: int = 100, seed: int = 0, profile_steps: int = 10,
               horizon: Optional[int] = None, iterations: int = 3, compile: bool = False,
               method: str = "ipm", freeze: bool = False) -> Timing:
    """Time ``steps`` control steps of ``task`` on a ``batch``-environment vector env from its seeded reset (swing-up
    and hold), after untimed warm-up steps; then profile ``profile_steps`` more to split the time into the
    method's parts (:func:`torchtraj.bench.profile.parts_of`, compiled or not). The warm-up is
    :data:`~torchtraj.core.recorded.TRACE_AT` steps, in which a controller's records are traced (a kernel that a
    step calls once, at the last of them), so that the timed steps are the controller's from then on; compiled
    (``compile``), 3 steps (kernels that first run at the second or third step compile there). ``warm_up_s`` is
    the warm-up's time. ``freeze``: ``gc.freeze()`` after the warm-up (undone after the profiled steps), so that
    Python's full collections skip the objects made until then (torch's modules among them)."""
    import gymnasium as gym

    venv = gym.make_vec(IDS[task], num_envs=batch)
    mpc = controller(task, venv, horizon=horizon, iterations=iterations, compile=compile, method=method)
    obs, _ = venv.reset(seed=seed)
    tick = time.perf_counter()
    for _ in range(3 if compile else TRACE_AT):
        obs, *_ = venv.step(mpc(obs))
    warm_up_s = time.perf_counter() - tick
    if freeze:
        gc.freeze()
    seconds, taken = [], []
    try:
        with FullCollections() as collections:
            for _ in range(steps):
                tick = time.perf_counter()
                actions = mpc(obs)
                seconds.append(time.perf_counter() - tick)
                taken.append(float(mpc.solution.iterations.max()))
                obs, *_ = venv.step(actions)
        state = {"obs": obs}

        def profiled_steps():
            for _ in range(profile_steps):
                state["obs"], *_ = venv.step(mpc(state["obs"]))

        parts = profile.split(profiled_steps, profile.parts_of(method, compile))[1]
    finally:
        if freeze:
            gc.unfreeze()
    return Timing(task, batch, mpc.problem.N, iterations, steps, 1e3 * float(np.median(seconds)),
                  1e3 * float(np.mean(seconds)), float(np.mean(taken)), parts, compile, warm_up_s,
                  1e3 * float(np.max(seconds)), collections.count, freeze)


# ---------------------------------------------------------------------------------------------- acceptance
def acceptance(task: str, num_envs: int = 100, episodes_per_env: int = 1, seed: int = 0, progress: bool = False,
               **controller_options) -> Run:
    """``num_envs × episodes_per_env`` episodes of ``task`` in one vector environment seeded ``seed``, one batched
    MPC call per step; with one episode per environment, episode ``i`` is the single environment seeded
    ``seed + i``. ``progress``: a bar on stderr (:func:`run_episodes`)."""
    import gymnasium as gym

    venv = gym.make_vec(IDS[task], num_envs=num_envs)
    return run_episodes(venv, controller(task, venv, **controller_options), episodes_per_env, seed,
                        progress=progress, label=task)


def pendulum_v1_example():
    """``examples/gym_pendulum_v1.py`` as a module (the Pendulum-v1 model lives with its example), or ``None``
    outside a source checkout."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "examples" / "gym_pendulum_v1.py"
    if not path.exists():
        return None
    spec = importlib.util.spec_from_file_location("gym_pendulum_v1", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# ---------------------------------------------------------------------------------------------- CLI
def _positive(text: str) -> int:
    """``--iterations``' value: a positive int, else argparse's error."""
    import argparse

    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"a positive number of iterations, not {text!r}")
    return int(text)


def parser():
    import argparse

    # each help text states its default once (argparse's defaults formatter repeated them)
    p = argparse.ArgumentParser(prog="python -m torchtraj.bench --mpc", description=__doc__.split("\n\n")[1])
    p.add_argument("--tasks", nargs="+", default=[*IDS, "pendulum_v1"], choices=[*IDS, "pendulum_v1"],
                   help="tasks to run; pendulum_v1 is Gymnasium's Pendulum-v1 (default: all)")
    p.add_argument("--episodes", type=int, default=100, help="seeded episodes per task (0: skip; default: 100)")
    p.add_argument("--vector-envs", type=int, default=64,
                   help="sub-environments of the autoreset run (0: skip; default: 64)")
    p.add_argument("--vector-episodes", type=int, default=2,
                   help="episodes per sub-environment in that run (default: 2)")
    p.add_argument("--v1-seeds", type=int, default=20, help="Pendulum-v1 episodes (0: skip; default: 20)")
    p.add_argument("--timing-batch", nargs="*", type=int, default=[1, 64],
                   help="B of the timing rows (none: skip; default: 1 64)")
    p.add_argument("--timing-steps", type=int, default=100, help="timed control steps per row (default: 100)")
    p.add_argument("--freeze-gc", action="store_true",
                   help="timing rows: gc.freeze() after the warm-up steps, so that Python's full garbage collections "
                        "skip the objects made until then (torch's modules among them)")
    p.add_argument("--compile", action="store_true",
                   help="run the episodes with torch.compile'd kernels (MPC(compile=True); "
                        "each batch size compiles first) "
                        "and time the policy both ways")
    p.add_argument("--method", default="ipm",
                   choices=[m for m in solvers.names() if solvers.get(m).handles_constraints],
                   help="the controllers' method (default: ipm, tt.MPC's, with its control-step options; altro runs "
                        "the tasks' options; Pendulum-v1's example keeps its own controller)")
    p.add_argument("--iterations", type=_positive, default=3,
                   help="solver iterations per control step (default: 3)")
    p.add_argument("--seed", type=int, default=0, help="seed of the first episode (default: 0)")
    p.add_argument("--threads", type=int, default=None, help="torch.set_num_threads (default: torch's choice)")
    return p


def main(argv: Optional[list] = None, out=None) -> int:
    import platform
    import sys

    args = parser().parse_args(argv)
    if args.compile:
        profile.quiet_inductor()
    out = out or sys.stdout

    def say(text: str = "") -> None:
        print(text, file=out, flush=True)

    if args.threads is not None:
        torch.set_num_threads(args.threads)
    say(f"torchtraj MPC bench: float64 on cpu, {torch.get_num_threads()} threads, torch {torch.__version__}, "
        f"python {platform.python_version()}; success definitions in torchtraj/bench/mpc.py")
    say(f"controllers: method {args.method}, {args.iterations} iterations per control step")
    chosen = {"method": args.method, "iterations": args.iterations}
    failed = False
    runs = [(f"{args.episodes} seeded ({args.seed}..{args.seed + args.episodes - 1})", args.episodes, 1, args.seed),
            (f"vector {args.vector_envs} envs x {args.vector_episodes} (autoreset)", args.vector_envs,
             args.vector_episodes, args.seed + 10_000)]
    say(f"{'task':<12}{'run':<40}{'episodes':>9}{'success':>9}{'rate':>7}{'return':>10}{'ms/step':>9}")
    for task in (t for t in args.tasks if t in IDS):
        for label, envs_, per_env, seed in runs:
            if envs_ < 1 or per_env < 1:
                continue
            run = acceptance(task, envs_, per_env, seed, progress=True, compile=args.compile, **chosen)
            wins = sum(SUCCESS[task](e) for e in run.episodes)
            rate = wins / len(run.episodes)
            failed |= rate < 0.95
            say(f"{task:<12}{label:<40}{len(run.episodes):>9}{wins:>9}{rate:>7.2f}"
                f"{np.mean([e.total for e in run.episodes]):>10.2f}{1e3 * np.median(run.step_seconds):>9.0f}")
    if "pendulum_v1" in args.tasks and args.v1_seeds > 0:
        example = pendulum_v1_example()
        if example is None:
            say("pendulum_v1: skipped (examples/gym_pendulum_v1.py is not here: run from a source checkout)")
        else:
            returns, theta, _ = example.run(args.v1_seeds, args.seed)
            upright = int((example.wrap(theta[:, -1]).abs() <= 0.1).sum())
            failed |= returns.mean() <= -200 or upright < args.v1_seeds
            say(f"{'pendulum_v1':<12}{f'{args.v1_seeds} seeds (Gymnasium Pendulum-v1)':<40}{args.v1_seeds:>9}"
                f"{upright:>9}{upright / args.v1_seeds:>7.2f}{returns.mean():>10.2f}"
                f"   (success: ends upright; target: mean return > -200)")
    if args.timing_batch:
        say()
        say("time per control step, pendulum (swing-up and hold from the seeded reset); profile shares of a step:")
        for compiled in (False, True) if args.compile else (False,):
            for batch in args.timing_batch:
                t = time_steps("pendulum", batch, args.timing_steps, args.seed,
                               profile_steps=min(10, args.timing_steps), compile=compiled, freeze=args.freeze_gc,
                               **chosen)
                where = (f"compiled (warm-up steps {t.warm_up_s:.0f} s); " if compiled else "eager; ")
                where += profile.format_split(t.parts)
                frozen = ", objects frozen" if t.frozen else ""
                say(f"B={batch:<4} horizon {t.horizon}, {t.iterations} iterations/step (mean used "
                    f"{t.iterations_mean:.2f}): {t.ms_median:.1f} ms median, {t.ms_mean:.1f} ms mean, "
                    f"{t.ms_max:.1f} ms max per step ({t.full_collections} full garbage collections{frozen}); "
                    f"{where}")
    say("rate: share of episodes meeting the task's success definition (target >= 0.95); return: mean episode "
        "return; ms/step: median time of one batched MPC call; timing rows: after "
        f"{TRACE_AT} untimed steps (3 compiled), in which the controller traces its records")
    return 1 if failed else 0
