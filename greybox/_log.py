"""greybox's `logging` logger, and Dask's logs routed through it.

A library does not print: its own messages go to the ``greybox`` logger (with a
`NullHandler`, so nothing shows unless the application configures logging), and Dask's
``distributed`` logs of a `greybox.fit_many` cluster are forwarded to ``greybox.dask``
instead of Dask's own terminal handler (a heartbeat `CommClosedError` at shutdown of a
healthy run is then a log record, not a traceback on the terminal).
"""

from __future__ import annotations

import logging

LOGGER = logging.getLogger("greybox")
LOGGER.addHandler(logging.NullHandler())
DASK_LOGGER = logging.getLogger("greybox.dask")


class _Forward(logging.Handler):
    """Hands each record to ``greybox.dask`` (its handlers, then greybox's and the root's)."""

    def emit(self, record: logging.LogRecord) -> None:
        if DASK_LOGGER.isEnabledFor(record.levelno):
            DASK_LOGGER.handle(record)


def route_dask_logs() -> None:
    """Replace the terminal handlers Dask installs on its loggers by a forward to
    ``greybox.dask`` (idempotent)."""
    for name in ("distributed", "dask"):
        lg = logging.getLogger(name)
        for h in list(lg.handlers):
            if not isinstance(h, _Forward):
                lg.removeHandler(h)
        if not any(isinstance(h, _Forward) for h in lg.handlers):
            lg.addHandler(_Forward())
        lg.propagate = False
