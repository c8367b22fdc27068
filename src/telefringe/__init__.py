"""telefringe: telecentric fringe-projection profilometry you can trust to the micrometre.

Decode phase-shifted fringe scans, calibrate a telecentric camera + projector rig,
reconstruct point clouds with per-point uncertainty, and measure (planes, marker
spacing, spheres, steps, BGA coplanarity). A virtual rig renders honest images of
known scenes so all of it runs without hardware.
"""

__version__ = "0.1.0"
