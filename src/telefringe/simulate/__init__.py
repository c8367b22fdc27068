"""The virtual rig: analytic scenes, an honest renderer and rig presets."""
