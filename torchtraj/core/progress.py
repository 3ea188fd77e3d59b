"""A one-line progress bar for long batched work: steps done, converged fraction, constraint violation.

    bench  [########··········]  41/100 steps  converged 97%  violation 3.2e-07  loss 1.4e-03  12 s

Written to ``sys.stderr`` (so a table on stdout stays clean). On a terminal the line is redrawn in place
(carriage return), at most every ``min_interval`` seconds; on anything else (a log file, a CI job) it prints a
plain line at every tenth of the total and at the end, so logs stay short. Nothing is drawn when ``enabled`` is
false: library calls (``tt.solve``) never draw one; the command-line tools and the examples' training loops turn
it on. ``TORCHTRAJ_PROGRESS=0`` in the environment turns every bar off, ``=1`` forces it on.

Reading a tensor's value synchronises with its device, so the bar reads ``converged`` and ``violation`` only when
it draws (a disabled bar reads nothing): a hot loop pays for a bar only as often as the bar is drawn.

Usage::

    with Progress(total=epochs, label="train") as bar:
        for epoch in range(epochs):
            ...
            bar.update(converged=sol.converged, violation=sol.max_violation, loss=float(loss))
"""

from __future__ import annotations

import math
import os
import sys
import time
from typing import Optional, TextIO

import torch

#: The environment variable that turns every bar off (``0``) or on (``1``), whatever the caller chose.
ENVIRONMENT_SWITCH = "TORCHTRAJ_PROGRESS"


def _fraction(converged) -> Optional[float]:
    """The converged fraction of a bool mask (tensor or array), or a number taken as the fraction itself."""
    if converged is None:
        return None
    if isinstance(converged, (bool, int, float)):
        return float(converged)
    mask = torch.as_tensor(converged)
    return float(mask.float().mean()) if mask.numel() else None


def _largest(violation) -> Optional[float]:
    """The largest entry of a violation tensor (or array), or a number as given; non-finite entries count."""
    if violation is None:
        return None
    if isinstance(violation, (int, float)):
        return float(violation)
    values = torch.as_tensor(violation).detach()
    return float(values.max()) if values.numel() else None


class Progress:
    """A progress bar (module docstring).

    Args:
        total: the number of steps the work takes (``None``: unknown, a counter without a bar).
        label: the word in front of the bar.
        unit: what one step is (``"steps"``, ``"episodes"``, ``"epochs"``...).
        enabled: draw the bar; ``TORCHTRAJ_PROGRESS`` in the environment overrides it.
        stream: where the bar goes; ``sys.stderr`` by default.
        min_interval: least seconds between two redraws on a terminal.
        width: characters of the bar itself.
    """

    def __init__(self, total: Optional[int] = None, label: str = "", unit: str = "steps", enabled: bool = True,
                 stream: Optional[TextIO] = None, min_interval: float = 0.2, width: int = 20):
        switch = os.environ.get(ENVIRONMENT_SWITCH)
        self.enabled = bool(enabled) if switch is None else switch not in ("0", "", "false", "no", "off")
        self.total = None if total is None else max(int(total), 0)
        self.label, self.unit, self.width, self.min_interval = label, unit, int(width), float(min_interval)
        self.stream = stream if stream is not None else sys.stderr
        self.count = 0
        self.fields: dict = {}
        self._start = time.perf_counter()
        self._drawn_at = -math.inf
        self._tenths_printed = -1
        self._visible = False  # a terminal line of ours that the next output must clear first
        isatty = getattr(self.stream, "isatty", None)
        self.interactive = bool(isatty()) if callable(isatty) else False

    # ------------------------------------------------------------------ the caller's side
    def update(self, n: int = 1, converged=None, violation=None, **values) -> None:
        """Advance by ``n`` steps and record the latest ``converged`` (a ``(B,)`` bool mask, or a fraction),
        ``violation`` (a ``(B,)`` tensor, whose largest entry is shown, or a number) and any other numbers to show
        (``loss=...``). Tensors are read only when the bar is drawn."""
        self.count += int(n)
        if converged is not None:
            self.fields["converged"] = converged
        if violation is not None:
            self.fields["violation"] = violation
        self.fields.update(values)
        if self.enabled:
            self._maybe_draw()

    def write(self, text: str, file: Optional[TextIO] = None) -> None:
        """Print ``text`` (a line of the caller's own output, to ``file``, by default the bar's stream) without
        tearing the bar: its line is cleared first and drawn again at the next update."""
        self.clear()
        print(text, file=self.stream if file is None else file, flush=True)

    def clear(self) -> None:
        """Erase the bar's line on a terminal (before other output); the next update draws it again."""
        if self._visible:
            self.stream.write("\r\033[K")
            self.stream.flush()
            self._visible = False
            self._drawn_at = -math.inf

    def close(self) -> None:
        """Draw the final state on its own line."""
        if self.enabled:
            self._draw(final=True)

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ drawing
    def line(self) -> str:
        """The bar as text (without carriage return or newline)."""
        parts = [self.label] if self.label else []
        if self.total:
            done = min(self.count / self.total, 1.0)
            filled = int(round(done * self.width))
            parts.append("[" + "#" * filled + "·" * (self.width - filled) + "]")
            parts.append(f"{self.count:>{len(str(self.total))}}/{self.total} {self.unit}")
        else:
            parts.append(f"{self.count} {self.unit}")
        fraction = _fraction(self.fields.get("converged"))
        if fraction is not None:
            parts.append(f"converged {100 * fraction:.0f}%")
        violation = _largest(self.fields.get("violation"))
        if violation is not None:
            parts.append(f"violation {violation:.1e}")
        for key, value in self.fields.items():
            if key not in ("converged", "violation"):
                parts.append(f"{key} {value:.3g}" if isinstance(value, float) else f"{key} {value}")
        parts.append(f"{time.perf_counter() - self._start:.0f} s")
        return "  ".join(parts)

    def _maybe_draw(self) -> None:
        if self.interactive:
            if time.perf_counter() - self._drawn_at >= self.min_interval:
                self._draw()
        elif self.total:
            tenths = int(10 * self.count / self.total)
            if tenths > self._tenths_printed and self.count < self.total:
                self._tenths_printed = tenths
                self._draw()

    def _draw(self, final: bool = False) -> None:
        text = self.line()
        if self.interactive:
            self.stream.write("\r\033[K" + text + ("\n" if final else ""))
            self._visible = not final
        elif final or self.total:
            self.stream.write(text + "\n")
        self.stream.flush()
        self._drawn_at = time.perf_counter()
