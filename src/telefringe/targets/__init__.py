"""The calibration target (a circle grid), its detection in images, ellipse fits and the
projector observations of its markers."""
