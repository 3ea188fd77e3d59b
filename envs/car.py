"""A unicycle that drives to a goal among circular obstacles, on ``torchtraj.models.unicycle`` (like ``car_3obs``).

State ``x = [x, y, θ]``, controls ``u = [v, ω]``::

    ẋ = v cos θ,   ẏ = v sin θ,   θ̇ = ω,     0 ≤ v ≤ 3,   |ω| ≤ 3

The car is a point. With goal ``g`` and obstacles ``(c_i, r_i)``, after each step::

    collided = ∃ i: ‖p_{k+1} − c_i‖ < r_i,     reached = not collided and ‖p_{k+1} − g‖ ≤ goal_radius
    r_k = (‖p_k − g‖ − ‖p_{k+1} − g‖) + 10 · reached − 10 · collided

The progress term telescopes to the distance covered towards the goal, so a return is bounded, and ending the
episode in an obstacle always costs more than any progress made before it. Collisions are checked at the steps
only; a step moves at most v dt = 0.15 < the smallest obstacle radius, so the car cannot jump over an obstacle.

Obstacle layout, drawn at every reset from the seeded generator (after the start state): ``num_obstacles``
circles of radius U(0.3, 0.5), centres ``s + t (g − s) + n ‖g − s‖ n̂`` with ``t ~ U(0.15, 0.85)``,
``n ~ U(−0.25, 0.25)``, ``n̂`` the unit normal of the start-goal line ``s → g``. A candidate circle is redrawn while
it comes within 0.5 of the nominal start or of the goal, or within 0.3 of another circle: the start and goal are
free, and every gap between obstacles is at least 0.3 wide, so no chain of circles can wall off the goal. A
partial layout that leaves no room for its next circle (500 draws fail) is dropped and drawn again whole.

The task as pure functions (:mod:`torchtraj.envs.core`), which the environment itself calls; the layout is
``{"obstacles": (..., n, 3)}``::

    dynamics(x, u, p)                          the RK4 step over dt = 0.05 of the model (no parameters)
    events(x_next, layout, params)             (collided, reached) after a step
    reward(x, u, x_next, layout, params)       r_k above
    terminated(x_next, layout, params)         collided or reached
    problem(params, horizon=30, margin=0.15)   the controller's Problem (CarEnv docstring)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Optional, Sequence

import numpy as np
import torch
from torch import Tensor

from torchtraj import models
from torchtraj.core.problem import Problem

from .core import DT, DTYPE, Layout, ModelEnv
from .render import Canvas
from .vector import ModelVectorEnv

SPEED_LIMIT, TURN_LIMIT = 3.0, 3.0  # the car_3obs problem's bounds
START_NOISE = 0.1  # half-width of the uniform draw of x0, y0, θ0 about the origin heading along +x
CLEARANCE, GAP = 0.5, 0.3  # free radius about start and goal beyond each circle; least gap between two circles
RADII = (0.3, 0.5)
GOAL_BONUS = COLLISION_PENALTY = 10.0
_MAX_LAYOUTS, _MAX_DRAWS = 100, 500


@dataclass(frozen=True)
class CarParams:
    """The car task's parameters (the unicycle model has none).

    Args:
        num_obstacles: circles drawn at every reset (module docstring).
        goal: the goal position ``(x, y)``, farther than 1 from the origin; stored as a tuple of floats.
        goal_radius: the episode ends, reached, within this distance of the goal.
        speed_limit, turn_limit: the bounds ``0 ≤ v ≤ speed_limit``, ``|ω| ≤ turn_limit``, the action space.
        start_noise: half-width of the uniform draw of x0, y0, θ0 about the origin heading along +x.
    """

    num_obstacles: int = 4
    goal: Sequence[float] = (3.0, 3.0)
    goal_radius: float = 0.2
    speed_limit: float = SPEED_LIMIT
    turn_limit: float = TURN_LIMIT
    start_noise: float = START_NOISE

    def __post_init__(self):
        goal = np.asarray(self.goal, dtype=np.float64)
        if goal.shape != (2,) or not np.all(np.isfinite(goal)) or np.linalg.norm(goal) <= 2 * CLEARANCE:
            raise ValueError(f"goal must be a finite (x, y) farther than {2 * CLEARANCE} from the origin, got {goal}")
        if int(self.num_obstacles) != self.num_obstacles or self.num_obstacles < 0:
            raise ValueError(f"num_obstacles must be a non-negative integer, got {self.num_obstacles!r}")
        if not self.goal_radius > 0:
            raise ValueError(f"goal_radius must be positive, got {self.goal_radius!r}")
        object.__setattr__(self, "goal", (float(goal[0]), float(goal[1])))  # hashable, as a frozen field should be
        object.__setattr__(self, "num_obstacles", int(self.num_obstacles))
        object.__setattr__(self, "goal_radius", float(self.goal_radius))

    def action_bounds(self) -> tuple[list[float], list[float]]:
        """``([v_min, ω_min], [v_max, ω_max])``: the action space and the controller's control bounds."""
        return [0.0, -self.turn_limit], [self.speed_limit, self.turn_limit]


#: The per-instance step ``(x (3,), u (2,), p) -> x_next (3,)`` the environment takes (the model has no ``p``).
dynamics = models.get("unicycle").discrete(DT, "rk4")


def events(x_next: Tensor, layout: Layout, params: CarParams) -> tuple[Tensor, Tensor]:
    """``(collided, reached)`` ``(...)`` after a step to ``x_next: (..., 3)`` among ``layout["obstacles"]``
    ``(..., n, 3)``: inside a circle; at the goal and not inside a circle."""
    circles = layout["obstacles"]
    gap = torch.linalg.vector_norm(x_next[..., None, :2] - circles[..., :2], dim=-1) - circles[..., 2]
    collided = (gap < 0).any(dim=-1)
    goal = torch.as_tensor(params.goal, dtype=x_next.dtype, device=x_next.device)
    distance = torch.linalg.vector_norm(x_next[..., :2] - goal, dim=-1)
    return collided, ~collided & (distance <= params.goal_radius)


def reward(x: Tensor, u: Tensor, x_next: Tensor, layout: Layout, params: CarParams) -> Tensor:
    """The environment's reward ``(...)``: progress towards the goal, plus the goal bonus, minus the collision
    penalty (module docstring)."""
    goal = torch.as_tensor(params.goal, dtype=x.dtype, device=x.device)
    progress = (torch.linalg.vector_norm(x[..., :2] - goal, dim=-1)
                - torch.linalg.vector_norm(x_next[..., :2] - goal, dim=-1))
    collided, reached = events(x_next, layout, params)
    return progress + GOAL_BONUS * reached.to(x.dtype) - COLLISION_PENALTY * collided.to(x.dtype)


def terminated(x_next: Tensor, layout: Layout, params: CarParams) -> Tensor:
    """Whether the step to ``x_next`` ended the episode ``(...)``: a collision or the goal reached."""
    collided, reached = events(x_next, layout, params)
    return collided | reached


def problem(params: Optional[CarParams] = None, horizon: int = 30, margin: float = 0.15) -> Problem:
    """The controller's :class:`~torchtraj.Problem` for a car of ``params`` (default ``CarParams()``): ``horizon``
    steps of :data:`dynamics` with the costs and constraints of :class:`CarEnv` ("Controller problem"), the
    obstacles inflated by ``margin``. Its ``obstacles`` parameter ``(n, 3)`` is a placeholder far away, replaced per
    call by the observed layouts ``(B, n, 3)``; ``x0`` is a placeholder: the controller passes the state."""
    params = CarParams() if params is None else params
    if not isinstance(params, CarParams):
        raise TypeError(f"params must be a CarParams, got {type(params).__name__}")
    dt, n = DT, params.num_obstacles

    def stage(x, u, p):
        d = x[:2] - p["goal"]
        return dt * ((d * d).sum() + 0.01 * (u * u).sum())

    def terminal(x, p):
        d = x[:2] - p["goal"]
        return 10.0 * (d * d).sum()

    def outside_obstacles(x, p):
        c = p["obstacles"]
        return (c[:, 2] + margin) ** 2 - (x[0] - c[:, 0]) ** 2 - (x[1] - c[:, 1]) ** 2

    low, high = (torch.tensor(b, dtype=torch.float64) for b in params.action_bounds())
    far = torch.tensor([1e3, 1e3, 0.1], dtype=torch.float64).expand(n, 3)
    return Problem(dynamics=dynamics, stage_cost=stage, terminal_cost=terminal,
                   x0=torch.zeros(3, dtype=torch.float64), horizon=horizon, nu=2,
                   params={"goal": torch.tensor(params.goal, dtype=torch.float64), "obstacles": far},
                   state_ineq=outside_obstacles if n else None, u_lower=low, u_upper=high,
                   u_init=torch.tensor([1.0, 0.0], dtype=torch.float64), dt=dt, name="car_mpc")


def place_obstacles(rng: np.random.Generator, goal: np.ndarray, count: int) -> np.ndarray:
    """``count`` circles ``(count, 3)`` rows ``(cx, cy, r)`` between the origin and ``goal`` (module docstring)."""
    start = np.zeros(2)
    axis = goal - start
    length = float(np.linalg.norm(axis))
    normal = np.array([-axis[1], axis[0]]) / length
    if count == 0:
        return np.zeros((0, 3))
    for _ in range(_MAX_LAYOUTS):
        circles: list[np.ndarray] = []
        # circle by circle; a layout whose first circles leave no room for the next one is dropped whole
        for _ in range(_MAX_DRAWS):
            t, n, r = rng.uniform(0.15, 0.85), rng.uniform(-0.25, 0.25), rng.uniform(*RADII)
            centre = start + t * axis + n * length * normal
            free = (np.linalg.norm(centre - start) >= r + CLEARANCE
                    and np.linalg.norm(centre - goal) >= r + CLEARANCE)
            if free and all(np.linalg.norm(centre - c[:2]) >= r + c[2] + GAP for c in circles):
                circles.append(np.array([centre[0], centre[1], r]))
                if len(circles) == count:
                    return np.array(circles)
    raise ValueError(f"could not place {count} obstacles between the start and goal {goal.tolist()}: "
                     "use fewer obstacles or a farther goal")


class CarEnv(ModelEnv):
    """Drive a unicycle to a goal through a seeded field of circular obstacles.

    ## Description

    The kinematic unicycle (Dubins car with turning in place) ``torchtraj.models.get("unicycle")``, stepped with
    RK4 at ``dt = 0.05`` s (``model.discrete(dt, "rk4")``), must reach ``goal`` (default (3, 3), as in the
    problem set's ``car_3obs``) without touching any of ``num_obstacles`` circles whose layout is drawn from the seed
    at every reset (module docstring). A controller reads the layout from ``obstacles`` ``(n, 3)`` rows
    ``(cx, cy, r)`` or from the observation.

    ## Action Space

    ``Box([0, -3], [3, 3], (2,), float64)``: forward speed v and turn rate ω. Out-of-bounds actions are clipped to
    the bounds; a NaN action raises ``ValueError``.

    ## Observation Space

    ``Box(-inf, inf, (3 + 3 n,), float64)``: the model state ``[x, y, θ]`` followed by the obstacle rows
    ``(cx, cy, r)`` flattened (n = ``num_obstacles``): the layout changes every episode, so it is observed.
    ``observation_to_state(obs) = obs[..., :3]``, ``observation_to_obstacles(obs)`` gives ``(..., n, 3)``.

    ## Rewards

    ``r = (‖p − g‖ − ‖p' − g‖) + 10 · reached − 10 · collided``: progress towards the goal, a bonus for reaching
    it and a penalty for hitting an obstacle.

    ## Starting State

    ``x0, y0, θ0`` uniform in [−0.1, 0.1] (at the origin, heading along +x), then the layout.

    ## Episode End

    Terminated on collision (‖p − c_i‖ < r_i) or on reaching the goal (‖p − g‖ ≤ ``goal_radius``, default 0.2),
    checked after each step; ``info`` says which (``"collided"``, ``"reached_goal"``). Truncated after
    ``max_episode_steps`` steps (default 200, i.e. 10 s; a straight run at full speed takes 1.4 s).

    ## Controller Problem

    ``env.problem(horizon=30, margin=0.15)`` (``torchtraj.envs.car.problem(env.params, ...)``) is the MPC controller's
    :class:`torchtraj.Problem`, on the environment's own step (:data:`dynamics`), with ``p`` the car's position and
    ``g`` the goal::

        minimise  Σ_k dt (‖p_k − g‖² + 0.01 ‖u_k‖²) + 10 ‖p_N − g‖²,   0 ≤ v_k ≤ 3,   |ω_k| ≤ 3,
                  ‖p_k − c_i‖ ≥ r_i + margin for each obstacle i,   N = 30 (1.5 s)

    The reward's progress term is the decrease of ‖p − g‖; the costs pull the same way, squared, so that they
    are smooth at the goal, and the terminal cost stands in for the rest of the episode. The reward's collision
    penalty is a constraint instead, its goal bonus implied by the costs. The obstacles are a per-instance
    parameter ``(n, 3)``, read from each observation; they are inflated by ``margin = 0.15`` because an augmented
    Lagrangian meets a constraint only approximately within 3 iterations (with 0.05, 3 of 32 seeds clip an
    obstacle; with 0.15, none of 192).

    ## Arguments

    ``gymnasium.make("torchtraj/Car-v0", num_obstacles=4, goal=(3.0, 3.0), goal_radius=0.2, render_mode=None)``, or
    ``CarEnv(max_episode_steps=200, num_obstacles=4, goal=(3.0, 3.0), goal_radius=0.2, render_mode=None)``.
    ``render_mode="rgb_array"`` draws a 400 × 400 frame. ``reset(options={"state": x0})`` starts from a given
    state (the layout is still drawn). ``gymnasium.make_vec`` gives :class:`CarVectorEnv`.
    """

    def __init__(self, max_episode_steps: int = 200, num_obstacles: int = 4, goal: Sequence[float] = (3.0, 3.0),
                 goal_radius: float = 0.2, render_mode: Optional[str] = None):
        self.params = CarParams(num_obstacles=num_obstacles, goal=goal, goal_radius=goal_radius)
        low, high = self.params.action_bounds()
        super().__init__(models.get("unicycle"), low, high, 3 + 3 * self.params.num_obstacles, max_episode_steps,
                         render_mode, dynamics)
        self._goal = torch.as_tensor(self.params.goal, dtype=DTYPE)

    @property
    def num_obstacles(self) -> int:
        """Circles drawn at every reset: ``params.num_obstacles``."""
        return self.params.num_obstacles

    @property
    def goal_radius(self) -> float:
        """The episode ends, reached, within this distance of the goal: ``params.goal_radius``."""
        return self.params.goal_radius

    def problem(self, horizon: int = 30, margin: float = 0.15) -> Problem:
        """The controller's problem (``## Controller Problem``): ``torchtraj.envs.car.problem(self.params, ...)``."""
        return problem(self.params, horizon, margin)

    @property
    def goal(self) -> Tensor:
        """The goal position ``(2,)`` (float64 tensor); the heading at the goal is free."""
        return self._goal.clone()

    @property
    def obstacles(self) -> Tensor:
        """This episode's obstacles ``(n, 3)`` rows ``(cx, cy, r)`` (float64 tensor, a copy)."""
        if "obstacles" not in self._layout:
            raise RuntimeError("the obstacles are drawn at reset(); call reset() first")
        return self._layout["obstacles"].clone()

    def observation_to_obstacles(self, obs):
        """The obstacle rows ``(..., n, 3)`` of observations ``(..., 3 + 3 n)``, numpy or torch."""
        circles = obs[..., 3:].reshape(*obs.shape[:-1], self.num_obstacles, 3)
        return circles.clone() if isinstance(circles, Tensor) else np.array(circles, dtype=np.float64)

    def _sample(self, rng: np.random.Generator):
        noise = self.params.start_noise
        x0 = rng.uniform(-noise, noise, size=3)
        return x0, {"obstacles": place_obstacles(rng, self._goal.numpy(), self.num_obstacles)}

    def _observe(self, x: Tensor, layout: Layout) -> Tensor:
        return torch.cat([x, layout["obstacles"].flatten(1)], dim=1)

    def _reward(self, x: Tensor, u: Tensor, x_next: Tensor, layout: Layout) -> Tensor:
        return reward(x, u, x_next, layout, self.params)

    def _terminated(self, x_next: Tensor, layout: Layout) -> Tensor:
        return terminated(x_next, layout, self.params)

    def _info(self, x_next: Tensor, layout: Layout) -> dict[str, Tensor]:
        collided, reached = events(x_next, layout, self.params)
        return {"collided": collided, "reached_goal": reached}

    def _draw(self, x: np.ndarray, layout: Mapping[str, np.ndarray]) -> np.ndarray:
        goal = self._goal.numpy()
        low, high = np.minimum(goal, 0.0) - 1.0, np.maximum(goal, 0.0) + 1.0
        canvas = Canvas(400, 400, (low[0], high[0], low[1], high[1]), background=(245, 245, 240))
        for cx, cy, r in layout["obstacles"]:
            canvas.disc((cx, cy), r, (120, 120, 130))
        canvas.disc(goal, self.goal_radius, (60, 180, 75))
        canvas.disc(x[:2], 0.08, (40, 80, 200))
        nose = (x[0] + 0.2 * np.cos(x[2]), x[1] + 0.2 * np.sin(x[2]))  # heading
        canvas.segment(x[:2], nose, 0.04, (20, 40, 120))
        return canvas.image


class CarVectorEnv(ModelVectorEnv):
    """``num_envs`` :class:`CarEnv` stepped as one batched torch operation (see :mod:`torchtraj.envs.vector`).

    ``CarVectorEnv(num_envs, device="cpu", array_type="numpy", render_mode=None, max_episode_steps=200,
    num_obstacles=4, goal=(3.0, 3.0), goal_radius=0.2)``; ``gymnasium.make_vec("torchtraj/Car-v0", ...)``
    builds it. ``obstacles`` is ``(B, n, 3)``; each sub-environment draws its own layout at each reset.
    """

    env_class = CarEnv

    @property
    def goal(self) -> Tensor:
        """The goal position ``(2,)`` shared by all sub-environments (float64 tensor on ``device``)."""
        return self.single_env.goal.to(self.device)

    @property
    def obstacles(self) -> Tensor:
        """The current obstacles ``(B, n, 3)`` of every sub-environment (float64 tensor on ``device``, a copy)."""
        if self._x is None:
            raise RuntimeError("the obstacles are drawn at reset(); call reset() first")
        return self._layout["obstacles"].clone()

    def observation_to_obstacles(self, obs):
        """The obstacle rows ``(..., n, 3)`` of observations ``(..., 3 + 3 n)``, numpy or torch."""
        return self.single_env.observation_to_obstacles(obs)
