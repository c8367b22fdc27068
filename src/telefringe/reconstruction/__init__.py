"""Point clouds from decoded scans: triangulation, height maps, the scan pipeline."""
