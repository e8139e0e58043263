"""The simulator side of deployment (needs JAX and MuJoCo): the export writer, the simulated
station, `ttmjx robot serve` and the latency sweeps; see deploy/__init__.py."""
