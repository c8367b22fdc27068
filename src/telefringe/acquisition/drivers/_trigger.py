"""The stale-frame bookkeeping shared by the aravis, gentl and pylon camera drivers."""

from __future__ import annotations

from telefringe.acquisition.base import DeviceError, Trigger

__all__ = ["SoftwareTriggerBook"]


class SoftwareTriggerBook:
    """Mixin: under ``Trigger.SOFTWARE`` a driver counts the triggers fired and not yet
    answered (``_owed``), follows the frame ids (``_last_id``) and remembers that a grab
    timed out while a frame was owed (``_desync``: that frame may still arrive, so
    acquisition restarts before the next trigger or after a flush).

    The driver provides ``settings``, ``discarded``, ``_acquiring()`` (bool) and
    ``_restart()`` (restarts acquisition and calls :meth:`_reset_counts`).
    """

    def _reset_counts(self) -> None:
        self._owed = 0              # software triggers fired and not yet answered
        self._last_id: int | None = None
        self._desync = False

    def _fire_ready(self) -> bool:
        """Before a software trigger: DeviceError when not acquiring; False when the camera
        is not on software trigger (``fire`` is then a no-op); a pending desync restarts
        acquisition first."""
        if not self._acquiring():
            raise DeviceError("start() the camera before fire()")
        if self.settings.trigger is not Trigger.SOFTWARE:
            return False
        if self._desync:
            self._restart()
        return True

    def _flushed(self, n: int) -> int:
        """After ``n`` queued frames were dropped by ``flush``: restart if a frame is owed
        or overdue, count them as discarded, return ``n``."""
        if self._desync or self._owed:
            self._restart()
        self.discarded += n
        return n
