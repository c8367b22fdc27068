"""Images -> projector coordinates: the scan in memory, patterns, wrapped phase, temporal
unwrapping, the projector nonlinearity (gamma), decoding and its fast kernels."""
