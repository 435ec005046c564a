"""The simulated R.T.A. X-MIND K: its device and its ASCII line (`sim`)."""
