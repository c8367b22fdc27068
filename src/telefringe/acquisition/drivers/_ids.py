"""Frame-id arithmetic shared by the camera drivers."""

from __future__ import annotations

__all__ = ["id_gap"]


def id_gap(last: int, new: int, *, wrap16: bool) -> int:
    """Frames from id ``last`` to id ``new`` (1 when ``new`` directly follows).

    With ``wrap16`` (GigE Vision 1.x block ids) ids run 1..65535 and 65535 is followed by
    1 (0 is never used); otherwise ids are 64-bit counters.

    >>> id_gap(65535, 1, wrap16=True), id_gap(65534, 2, wrap16=True), id_gap(7, 8, wrap16=True)
    (1, 3, 1)
    >>> id_gap(5, 5, wrap16=True)
    0
    """
    if wrap16 and 1 <= last <= 65535 and 1 <= new <= 65535:
        return (new - last) % 65535
    return new - last
