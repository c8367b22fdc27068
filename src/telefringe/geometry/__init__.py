"""Pure maths with no devices: rotations (so3), distortion models, rays."""
