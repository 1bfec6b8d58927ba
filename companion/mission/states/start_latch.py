"""An operator's start, kept from the tick it is asked until a state acts on it; pure.

A start is asked for on one tick (``companion start``) or held (``service.auto_start``): it is taken on its
rising edge, and only where a state can act on it (elsewhere it is dropped, never kept for later). A
takeover is the same for a start that may also take a vehicle already flying (an operator's, not
``auto_start``'s). The phases that act on it (launch, and PX4's modes for a start after a hold) spend it;
a start the operator was told was refused is withdrawn the same way.
"""

from __future__ import annotations


class StartLatch:
    """The latched start and takeover; written only through :meth:`update` and :meth:`spend`."""

    def __init__(self) -> None:
        #: A start waits to be acted on.
        self.requested = False
        #: That start may take a vehicle already in the air.
        self.takeover = False
        self._prev_start = False
        self._prev_takeover = False

    def update(self, start: bool, takeover: bool, *, actionable: bool) -> None:
        """This tick's requests; a rising edge latches where ``actionable`` (a state can act on it)."""
        if start and not self._prev_start and actionable:
            self.requested = True
        self._prev_start = start
        if takeover and not self._prev_takeover and actionable:
            self.takeover = True
        self._prev_takeover = takeover

    def spend(self) -> None:
        """The start was acted on, dropped or withdrawn: nothing waits any more."""
        self.requested = False
        self.takeover = False
