"""The simulated Lika RD4: its device and its Modbus RTU line (`sim`)."""
