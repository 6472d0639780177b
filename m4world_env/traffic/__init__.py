"""The highway-env traffic bridge: scenario + ego action -> one SceneFrame per sensor tick."""

from m4world_env.traffic.actions import META_ACTIONS, ActionConfig, ActionError
from m4world_env.traffic.bridge import BridgeConfig, TrafficBridge
from m4world_env.traffic.population import UnknownObjectError

__all__ = [
    "META_ACTIONS",
    "ActionConfig",
    "ActionError",
    "BridgeConfig",
    "TrafficBridge",
    "UnknownObjectError",
]
