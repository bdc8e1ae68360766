"""`python -m mecanum_drive.ros2`: the ROS 2 bridge (see `mecanum_drive.ros2`)."""

import sys

from . import main

sys.exit(main())
