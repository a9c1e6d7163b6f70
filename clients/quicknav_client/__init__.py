"""QuickNav Python SDK: talks to a QuickNav service without importing JAX."""

from importlib.metadata import PackageNotFoundError as _NotInstalled
from importlib.metadata import version as _version

try:  # one source: clients/pyproject.toml's version, as installed
    __version__ = _version("quicknav-client")
except _NotInstalled:  # the source folder on sys.path without the package installed
    __version__ = "0+unknown"

# --- REST jobs client (rest.py, errors.py) ------------------------------------------------------
from quicknav_client.errors import (
    BadRequest,
    Conflict,
    ConnectionFailed,
    NotFound,
    PayloadTooLarge,
    QuickNavError,
    ServerError,
    Unauthorized,
    WaitTimeout,
)
from quicknav_client.rest import (
    AsyncJob,
    AsyncQuickNavClient,
    Job,
    JobList,
    QuickNavClient,
)

__all__ = [
    "AsyncJob",
    "AsyncQuickNavClient",
    "BadRequest",
    "Conflict",
    "ConnectionFailed",
    "Job",
    "JobList",
    "NotFound",
    "PayloadTooLarge",
    "QuickNavClient",
    "QuickNavError",
    "ServerError",
    "Unauthorized",
    "WaitTimeout",
    "__version__",
]
# --- end of the REST block (other parts: extend with `__all__ += [...]`) ---------------------

# --- gRPC rollouts (rollout.py) and gymnasium adapters (gym.py, needs the `gym` extra) ----------
from quicknav_client.rollout import RemotePolicy, RolloutClient, RolloutError, Started, Transition

__all__ += [
    "RemoteEnv",
    "RemotePolicy",
    "RemoteVectorEnv",
    "RolloutClient",
    "RolloutError",
    "Started",
    "Transition",
]


def __getattr__(name: str):
    # gymnasium is optional: import the adapters only when asked for
    if name in ("RemoteEnv", "RemoteVectorEnv"):
        from quicknav_client import gym

        return getattr(gym, name)
    raise AttributeError(f"module 'quicknav_client' has no attribute {name!r}")
