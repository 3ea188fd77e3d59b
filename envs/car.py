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
"""

from __future__ import annotations

from typing import Mapping, Optional, Sequence

import numpy as np
import torch
from torch import Tensor

from torchtraj import models

from .core import DTYPE, Layout, ModelEnv
from .render import Canvas
from .vector import ModelVectorEnv

SPEED_LIMIT, TURN_LIMIT = 3.0, 3.0  # the car_3obs problem's bounds
START_NOISE = 0.1  # half-width of the uniform draw of x0, y0, θ0 about the origin heading along +x
CLEARANCE, GAP = 0.5, 0.3  # free radius about start and goal beyond each circle; least gap between two circles
RADII = (0.3, 0.5)
GOAL_BONUS = COLLISION_PENALTY = 10.0
_MAX_LAYOUTS, _MAX_DRAWS = 100, 500


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

    ## Arguments

    ``gymnasium.make("torchtraj/Car-v0", num_obstacles=4, goal=(3.0, 3.0), goal_radius=0.2, render_mode=None)``, or
    ``CarEnv(max_episode_steps=200, num_obstacles=4, goal=(3.0, 3.0), goal_radius=0.2, render_mode=None)``.
    ``render_mode="rgb_array"`` draws a 400 × 400 frame. ``reset(options={"state": x0})`` starts from a given
    state (the layout is still drawn). ``gymnasium.make_vec`` gives :class:`CarVectorEnv`.
    """

    def __init__(self, max_episode_steps: int = 200, num_obstacles: int = 4, goal: Sequence[float] = (3.0, 3.0),
                 goal_radius: float = 0.2, render_mode: Optional[str] = None):
        goal = np.asarray(goal, dtype=np.float64)
        if goal.shape != (2,) or not np.all(np.isfinite(goal)) or np.linalg.norm(goal) <= 2 * CLEARANCE:
            raise ValueError(f"goal must be a finite (x, y) farther than {2 * CLEARANCE} from the origin, got {goal}")
        if int(num_obstacles) != num_obstacles or num_obstacles < 0:
            raise ValueError(f"num_obstacles must be a non-negative integer, got {num_obstacles!r}")
        if not goal_radius > 0:
            raise ValueError(f"goal_radius must be positive, got {goal_radius!r}")
        super().__init__(models.get("unicycle"), [0.0, -TURN_LIMIT], [SPEED_LIMIT, TURN_LIMIT],
                         3 + 3 * int(num_obstacles), max_episode_steps, render_mode)
        self.num_obstacles = int(num_obstacles)
        self.goal_radius = float(goal_radius)
        self._goal = torch.as_tensor(goal, dtype=DTYPE)

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
        x0 = rng.uniform(-START_NOISE, START_NOISE, size=3)
        return x0, {"obstacles": place_obstacles(rng, self._goal.numpy(), self.num_obstacles)}

    def _observe(self, x: Tensor, layout: Layout) -> Tensor:
        return torch.cat([x, layout["obstacles"].flatten(1)], dim=1)

    def _events(self, x_next: Tensor, layout: Layout) -> tuple[Tensor, Tensor]:
        """``(collided, reached)`` ``(B,)`` after a step."""
        circles = layout["obstacles"]  # (B, n, 3)
        gap = torch.linalg.vector_norm(x_next[:, None, :2] - circles[..., :2], dim=-1) - circles[..., 2]
        collided = (gap < 0).any(dim=1)
        distance = torch.linalg.vector_norm(x_next[:, :2] - self._goal.to(x_next.device), dim=-1)
        return collided, ~collided & (distance <= self.goal_radius)

    def _reward(self, x: Tensor, u: Tensor, x_next: Tensor, layout: Layout) -> Tensor:
        goal = self._goal.to(x.device)
        progress = (torch.linalg.vector_norm(x[:, :2] - goal, dim=-1)
                    - torch.linalg.vector_norm(x_next[:, :2] - goal, dim=-1))
        collided, reached = self._events(x_next, layout)
        return progress + GOAL_BONUS * reached.to(x.dtype) - COLLISION_PENALTY * collided.to(x.dtype)

    def _terminated(self, x_next: Tensor, layout: Layout) -> Tensor:
        collided, reached = self._events(x_next, layout)
        return collided | reached

    def _info(self, x_next: Tensor, layout: Layout) -> dict[str, Tensor]:
        collided, reached = self._events(x_next, layout)
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
    """``num_envs`` :class:`CarEnv` stepped as one batched torch operation (see :mod:`envs.vector`).

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
