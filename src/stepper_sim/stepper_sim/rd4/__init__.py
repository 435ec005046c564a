"""The simulated Lika RD4: its device (`device`, its Control Word in `control`) and its Modbus RTU
line (`sim`)."""
