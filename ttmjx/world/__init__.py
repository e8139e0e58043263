"""The world: configuration, scene, ball physics, throws, the one-throw task and its events, the trajectory record, the observation layout and the two physics backends (MJX and MuJoCo C)."""
