"""Iterations shared by several solvers: one (AL-)iLQR iteration (:mod:`.ilqr`)."""
