"""python -m stepper_drivers.cli: the same as the stepperctl executable."""

import sys

from .main import main

sys.exit(main())
