"""Camera and projector drivers, one module per driver name of the registry
(:data:`telefringe.acquisition.base.CAMERA_DRIVERS`, ``PROJECTOR_DRIVERS``); each imports its
optional package at module level and is imported only when asked for."""
