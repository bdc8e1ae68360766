"""Drive a mecanum robot running the mecanum-drive firmware from Linux, over any python-can bus.

```python
from mecanum_drive import Robot

with Robot.open(channel="can0", interface="socketcan") as robot:
    robot.enable()
    robot.wait_state("ENABLED", timeout=1.0)
    robot.drive(0.3, 0.0, 0.0)          # m/s, m/s, rad/s; streamed at 50 Hz
    ...
# Leaving the block (or an exception, or the interpreter's exit) stops the stream, sends a
# zero twist and disables the robot.
```

The command line `mecanum-drive` (`mecanum-drive --help`) does the same from a shell.
"""

from .protocol import database, protocol_version
from .robot import (
    Counters,
    Heartbeat,
    NotResponding,
    Odometry,
    ProtocolMismatch,
    Robot,
    RobotError,
    RobotFault,
    Slip,
    Status,
    WheelTestResult,
)

__all__ = [
    "Counters",
    "Heartbeat",
    "NotResponding",
    "Odometry",
    "ProtocolMismatch",
    "Robot",
    "RobotError",
    "RobotFault",
    "Slip",
    "Status",
    "WheelTestResult",
    "database",
    "protocol_version",
]
__version__ = "0.1.0"
