"""Tools that use the world without defining it: the scripted striker, the ES policy, thrower calibration, bootstrap demonstrations, rendering and benchmarks."""
