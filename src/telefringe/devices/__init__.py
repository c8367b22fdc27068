"""What a camera or projector is: the Device protocol and one file per model, and the rig
that holds them in one world frame."""
