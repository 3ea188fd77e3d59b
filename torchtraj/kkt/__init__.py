"""The linear-quadratic (KKT) model of a problem at a point, shared by every solver and the implicit layer."""

from .model import cost_model, total_cost

__all__ = ["cost_model", "total_cost"]
