"""What all service nodes share: session from config, codec, typed pub/sub/query, liveliness, shutdown."""

from services.runtime.client import AliveWatcher, alive_services, query
from services.runtime.config import (
    HUB_PORT,
    add_bus_arguments,
    config_from_args,
    deploy_file,
    load_config,
    loopback_config,
)
from services.runtime.errors import QueryError, QueryFailed
from services.runtime.node import Node, TypedPublisher
from services.runtime.params import QueryParams
from services.runtime.service import (
    finite_float,
    nonnegative_float,
    nonnegative_int,
    positive_float,
    service_main,
    setup_logging,
    shutdown_event,
)

__all__ = [
    "HUB_PORT", "AliveWatcher", "Node", "QueryError", "QueryFailed", "QueryParams", "TypedPublisher",
    "add_bus_arguments", "alive_services", "config_from_args", "deploy_file", "load_config",
    "loopback_config", "finite_float", "nonnegative_float", "nonnegative_int", "positive_float", "query",
    "service_main", "setup_logging", "shutdown_event",
]
