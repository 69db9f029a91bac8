"""What a dataset is: its label configuration, its profile (sensor, projection, voting rule),
its folder layout, the spherical projection of its scans, distance bands and profile statistics."""
