"""ArrayTac 4 x 4 pin display driver: base class, CAN FD and serial backends, the frame codec,
and the emulated drive-board firmware. Open one with :func:`local_site.devices.open_display`.
"""

from local_site.display.base import (
    AppliedPinCommand,
    ArrayTacDisplay,
    DisplayStats,
    PinFeedback,
    SafeMode,
)

__all__ = ["AppliedPinCommand", "ArrayTacDisplay", "DisplayStats", "PinFeedback", "SafeMode"]
