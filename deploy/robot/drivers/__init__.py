"""Drivers for the real cell (optional extra: `pip install -e '.[robot]'`), one file per device,
each implementing deploy/robot/hardware.py's interfaces on the runner's clock:

  egm.py      the ABB arm over Externally Guided Motion (abb-robot-client, UDP + ABB's protobuf)
  gantry.py   the Festo two-axis gantry over Modbus TCP (pymodbus), polled on its own thread
  tracker.py  the ball tracker's UDP stream (wire format in its docstring)
  cell.py     one Robot joining arm and gantry into the 8 joints, the cell config (TOML), and
              `ttmjx robot run --station cell`
  faults.py   the drivers' fault log (what went wrong on the wire, per device, timestamped)

deploy/sim/serve.py serves the simulated station over the same protocols (`ttmjx robot serve`).
Bringing up a real cell: docs/ROBOT.md.
"""
