"""The simulated CiA 402 slave: power state machine, set-point handshake, profiles."""
