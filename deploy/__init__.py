"""From a trained policy to the robot, in two rooms:

- deploy/robot/: the robot side, what a robot's computer installs (`pip install ttmjx[robot]`:
  numpy, safetensors, tyro; onnxruntime for the ONNX graph; the cell's drivers). It reads
  exports, runs the policy, the runner, the safety filters and the drivers, and never imports
  JAX, MuJoCo or the trainer.
- deploy/sim/: the simulator side, which needs the simulator and the trainer: it writes exports
  from checkpoints, simulates the cell as a station (in process, or over the cell's network
  protocols with `ttmjx robot serve`) and sweeps latencies.

The robot side reaches the simulated station only over the network protocols, as it reaches the
real cell; the simulator side uses the robot side (the runner plays on its station).
"""
