"""Link health, one small state machine: connected, retrying, outage.

The adapter reconnects by itself (back-off and jitter in :class:`cnc_adapters.base.Link`); this
machine only tracks what the runtime must do about it: no write while the link is down, an
``OUTAGE`` alarm once it has been down longer than ``max_outage_s``, and a fresh write of the
offset once it is back (the controller may have lost the value).
"""

from __future__ import annotations

import enum


class LinkState(enum.Enum):
    CONNECTED = "connected"
    RETRYING = "retrying"
    OUTAGE = "outage"


class LinkHealth:
    """Events: :meth:`failed` (the controller cannot be reached) and :meth:`succeeded`."""

    def __init__(self, max_outage_s: float):
        self.max_outage_s = max_outage_s
        self.state = LinkState.CONNECTED
        self.down_since: float | None = None

    @property
    def up(self) -> bool:
        return self.state is LinkState.CONNECTED

    def failed(self, now: float) -> LinkState:
        """The link is down at ``now``: retrying, and an outage once down long enough."""
        if self.down_since is None:
            self.down_since = now
            self.state = LinkState.RETRYING
        elif now - self.down_since > self.max_outage_s:
            self.state = LinkState.OUTAGE
        return self.state

    def succeeded(self, now: float) -> float | None:
        """The link answered at ``now``; how long it had been down, or None if it was up."""
        if self.down_since is None:
            return None
        down = now - self.down_since
        self.down_since = None
        self.state = LinkState.CONNECTED
        return down
