"""State-space models and the scenarios of the papers."""

from gmjax.models._base import StateSpaceModel as StateSpaceModel

__all__ = ["StateSpaceModel"]
