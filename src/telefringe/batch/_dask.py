"""The Dask parts of a batch that need ``distributed`` at import (imported only when a batch
runs on Dask)."""

from __future__ import annotations

from distributed.diagnostics.plugin import WorkerPlugin

from telefringe.batch.job import install_rig, remove_rig

__all__ = ["RigPlugin"]


class RigPlugin(WorkerPlugin):
    """Keeps a rig in every worker process: sent once to each worker, and to every worker
    that joins or restarts later (a scattered rig would be lost with the last worker
    holding it)."""

    def __init__(self, digest: str, rig):
        self.name = f"telefringe-rig-{digest[:16]}"
        self.digest = digest
        self.rig = rig

    def setup(self, worker):
        install_rig(self.digest, self.rig)

    def teardown(self, worker):
        remove_rig(self.digest)
