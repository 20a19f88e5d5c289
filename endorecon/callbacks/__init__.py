"""Lightning callbacks of the bootstrapping loop."""

from endorecon.callbacks.bootstrap import BootstrapCallback
from endorecon.callbacks.last_checkpoint import LastCheckpoint

__all__ = ["BootstrapCallback", "LastCheckpoint"]
