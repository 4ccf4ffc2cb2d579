"""iarcs_env: the world of iARCS — rooms, floor plans, scenes, datasets, renders, metrics, the noise
schedule and the Gymnasium denoising MDP. It imports neither ``agents`` nor ``rewards``' synthesis code."""

from .floorplan import FloorPlan, FloorPlanError
from .rooms import ROOMS, RoomSpec, get_room
from .scene import Layout, SceneBatch, floor_features, floor_half_extents
from .stats import DatasetStats

__all__ = ["FloorPlan", "FloorPlanError", "ROOMS", "RoomSpec", "get_room", "Layout", "SceneBatch",
           "floor_features", "floor_half_extents", "DatasetStats"]

from .env import register_envs as _register_envs

_register_envs()
