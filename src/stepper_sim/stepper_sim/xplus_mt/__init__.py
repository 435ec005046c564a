"""The simulated R.T.A. X-PLUS MT: its device and its Modbus TCP server (`sim`)."""
