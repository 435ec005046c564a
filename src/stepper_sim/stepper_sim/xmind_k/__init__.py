"""The simulated R.T.A. X-MIND K: its device (`device`, its program engine in `program`) and its
ASCII line (`sim`)."""
