"""The control socket's intake: the measurements ``thermocomp measure`` sends, each handed to its
spindle (:mod:`.control` is the socket and its protocol)."""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from pathlib import Path

from .control import ControlChannel, Pending
from .events import event
from .spindle import SpindleRuntime


class Inbox:
    """The control socket, open once a spindle fuses measurements; each tick it takes, without
    blocking, the measurements sent and hands each to its spindle."""

    def __init__(self) -> None:
        self.channel: ControlChannel | None = None

    def open(self, state_dir: Path, clock: Callable[[], float]) -> None:
        """Listen on the control socket; one that cannot be opened is logged, and compensation
        goes on without it."""
        if self.channel is not None:
            return
        channel = ControlChannel(state_dir, clock)
        try:
            self.channel = channel.open()
        except OSError as err:
            event(
                "control_failed",
                None,
                "cannot listen on %s: %s; `thermocomp measure` will not reach this service",
                channel.path,
                err.strerror or err,
                level=logging.ERROR,
                path=str(channel.path),
                error=str(err)[:200],
            )

    def take(self, spindles: Mapping[str, SpindleRuntime]) -> None:
        """Hand every measurement waiting to its spindle."""
        if self.channel is not None:
            for request in self.channel.poll():
                _dispatch(request, spindles)

    def close(self) -> None:
        if self.channel is not None:
            self.channel.close()
            self.channel = None


def _dispatch(request: Pending, spindles: Mapping[str, SpindleRuntime]) -> None:
    """Hand a measurement to its spindle (named, or the only one with an observer)."""
    req = request.request
    assert req is not None
    fused = [name for name, rt in spindles.items() if rt.estimate.fused is not None]
    name = req.spindle
    if name is None:
        if len(fused) != 1:
            request.fail(f"name the spindle (--spindle): observers on {', '.join(fused) or 'none'}")
            return
        name = fused[0]
    rt = spindles.get(name)
    if rt is None:
        request.fail(f"no spindle {name!r}; spindles: {', '.join(spindles)}")
        return
    rt.submit(req.elongation_um, req.sigma_um, request.reply)
