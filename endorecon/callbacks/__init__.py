"""Lightning callbacks of the bootstrapping loop."""

from endorecon.callbacks.bootstrap import BootstrapCallback

__all__ = ["BootstrapCallback"]
