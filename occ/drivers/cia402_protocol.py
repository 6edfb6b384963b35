"""CANopen (CiA 301) and CiA 402 constants shared by the ``cia402`` driver and its emulator.

The tables' wording is this project's own; the codes are those of CiA 301 (SDO abort codes,
emergency error codes) and CiA 402 (the drive's state machine, its emergency codes). Neither
module needs anything else from the other: the emulator (occ/drivers/cia402_sim.py) imports
this one only, so it runs where the driver's dependencies are not wanted.
"""

from __future__ import annotations

__all__ = [
    "COB_NMT",
    "COB_SYNC",
    "COB_EMCY",
    "COB_TPDO",
    "COB_RPDO",
    "COB_SDO_TX",
    "COB_SDO_RX",
    "COB_HEARTBEAT",
    "NMT_STATES",
    "NMT_OPERATIONAL",
    "NMT_PRE_OPERATIONAL",
    "NMT_STOPPED",
    "NMT_BOOT",
    "CW_DISABLE_VOLTAGE",
    "CW_QUICK_STOP",
    "CW_SHUTDOWN",
    "CW_SWITCH_ON",
    "CW_ENABLE_OPERATION",
    "CW_FAULT_RESET",
    "STATUS_WORDS",
    "MODE_CSP",
    "MODE_CST",
    "SDO_ABORT_CODES",
    "EMCY_CODES",
    "cia402_state",
    "emcy_meaning",
    "sdo_abort_meaning",
    "frame_bits",
    "master_sends",
]

# ---------------------------------------------------------------- COB-IDs (CiA 301, predefined set)
COB_NMT = 0x000
COB_SYNC = 0x080
COB_EMCY = 0x080  # + node id (1-127)
COB_TPDO = (0x180, 0x280, 0x380, 0x480)  # + node id: node -> master
COB_RPDO = (0x200, 0x300, 0x400, 0x500)  # + node id: master -> node
COB_SDO_TX = 0x580  # + node id: the server's answers (node -> master)
COB_SDO_RX = 0x600  # + node id: the client's requests (master -> node)
COB_HEARTBEAT = 0x700  # + node id

# ---------------------------------------------------------------- NMT (CiA 301)
NMT_BOOT = 0x00
NMT_STOPPED = 0x04
NMT_OPERATIONAL = 0x05
NMT_PRE_OPERATIONAL = 0x7F
NMT_STATES = {
    NMT_BOOT: "BOOT-UP",
    NMT_STOPPED: "STOPPED",
    NMT_OPERATIONAL: "OPERATIONAL",
    NMT_PRE_OPERATIONAL: "PRE-OPERATIONAL",
}
#: NMT command specifiers (the first byte of a frame on COB-ID 0)
NMT_START = 0x01
NMT_STOP = 0x02
NMT_ENTER_PRE_OPERATIONAL = 0x80
NMT_RESET_NODE = 0x81
NMT_RESET_COMMUNICATION = 0x82

# ---------------------------------------------------------------- CiA 402 device control
CW_DISABLE_VOLTAGE = 0x00
CW_QUICK_STOP = 0x02
CW_SHUTDOWN = 0x06
CW_SWITCH_ON = 0x07  # also "disable operation" from OPERATION ENABLED
CW_ENABLE_OPERATION = 0x0F
CW_FAULT_RESET = 0x80  # on its rising edge

MODE_CSP = 8  # cyclic synchronous position
MODE_CST = 10  # cyclic synchronous torque

#: the statusword's state bits (mask, value, name) in CiA 402's order of evaluation
STATUS_WORDS: tuple[tuple[int, int, str], ...] = (
    (0x4F, 0x00, "NOT READY TO SWITCH ON"),
    (0x4F, 0x40, "SWITCH ON DISABLED"),
    (0x6F, 0x21, "READY TO SWITCH ON"),
    (0x6F, 0x23, "SWITCHED ON"),
    (0x6F, 0x27, "OPERATION ENABLED"),
    (0x6F, 0x07, "QUICK STOP ACTIVE"),
    (0x4F, 0x0F, "FAULT REACTION ACTIVE"),
    (0x4F, 0x08, "FAULT"),
)
SW_FAULT = 0x0008
SW_VOLTAGE_ENABLED = 0x0010
SW_QUICK_STOP = 0x0020  # 0 = quick stop active
SW_REMOTE = 0x0200
SW_TARGET_REACHED = 0x0400
SW_FOLLOWS_TARGET = 0x1000  # CSP: the drive follows the target position
SW_FOLLOWING_ERROR = 0x2000  # CSP: following error


def cia402_state(statusword: int) -> str:
    """The CiA 402 state a statusword shows (its name), or ``"UNKNOWN"``."""
    for mask, value, name in STATUS_WORDS:
        if statusword & mask == value:
            return name
    return "UNKNOWN"


# ---------------------------------------------------------------- SDO abort codes (CiA 301)
SDO_ABORT_CODES: dict[int, str] = {
    0x05030000: "toggle bit not alternated",
    0x05040000: "SDO protocol timed out",
    0x05040001: "client/server command specifier not valid or unknown",
    0x05040002: "invalid block size (block mode)",
    0x05040003: "invalid sequence number (block mode)",
    0x05040004: "CRC error (block mode)",
    0x05040005: "out of memory",
    0x06010000: "unsupported access to the object",
    0x06010001: "attempt to read a write-only object",
    0x06010002: "attempt to write a read-only object",
    0x06020000: "the object does not exist in the object dictionary",
    0x06040041: "the object cannot be mapped into a PDO",
    0x06040042: "the mapped objects would exceed the PDO's length",
    0x06040043: "general parameter incompatibility",
    0x06040047: "general internal incompatibility in the device",
    0x06060000: "access failed because of a hardware error",
    0x06070010: "data type does not match: length of the service parameter does not match",
    0x06070012: "data type does not match: service parameter too long",
    0x06070013: "data type does not match: service parameter too short",
    0x06090011: "the sub-index does not exist",
    0x06090030: "invalid value (download only)",
    0x06090031: "value written too high",
    0x06090032: "value written too low",
    0x06090036: "maximum value below minimum value",
    0x060A0023: "resource not available: SDO connection",
    0x08000000: "general error",
    0x08000020: "data cannot be transferred or stored to the application",
    0x08000021: "data cannot be transferred or stored: local control",
    0x08000022: "data cannot be transferred or stored in the device's present state",
    0x08000023: "no object dictionary (dynamic generation failed or none present)",
    0x08000024: "no data available",
}


def sdo_abort_meaning(code: int) -> str:
    """What an SDO abort code means (CiA 301), or that it is not a standard one."""
    return SDO_ABORT_CODES.get(code, "not a CiA 301 abort code (manufacturer specific?)")


# ---------------------------------------------------------------- emergency codes (CiA 301/402)
EMCY_CODES: dict[int, str] = {
    0x0000: "error reset or no error",
    0x1000: "generic error",
    0x2000: "current",
    0x2310: "continuous overcurrent (motor side)",
    0x2320: "short circuit or earth leakage (motor side)",
    0x3000: "voltage",
    0x3210: "DC link overvoltage",
    0x3220: "DC link undervoltage",
    0x4000: "temperature",
    0x4210: "excess temperature of the device",
    0x4310: "excess temperature of the drive (motor)",
    0x5000: "device hardware",
    0x5530: "data storage (non-volatile memory) error",
    0x6000: "device software",
    0x6100: "internal software error",
    0x7000: "additional modules",
    0x7300: "sensor (position or velocity feedback) error",
    0x7305: "incremental sensor 1 fault",
    0x7500: "communication",
    0x8000: "monitoring",
    0x8110: "CAN overrun (frames lost)",
    0x8120: "CAN controller error passive",
    0x8130: "life guard or heartbeat error (the master's heartbeat was lost)",
    0x8140: "recovered from bus-off",
    0x8210: "PDO not processed: length error",
    0x8400: "velocity controller: deviation too large",
    0x8611: "position controller: following error",
    0x8612: "position controller: reference limit",
    0x9000: "external error",
    0xFF00: "device specific",
}


def emcy_meaning(code: int) -> str:
    """What an emergency error code means: the exact code, else its class (CiA 301/402)."""
    for key in (code, code & 0xFFF0, code & 0xFF00, code & 0xF000):
        if key in EMCY_CODES:
            return EMCY_CODES[key]
    return "unknown error code"


# ---------------------------------------------------------------- bus timing
def frame_bits(data_bytes: int) -> int:
    """The longest a classic CAN frame with an 11-bit identifier and ``data_bytes`` bytes takes
    on the bus, in bit times, worst-case bit stuffing and the 3-bit inter-frame space included:
    ``55 + 10 * data_bytes`` (135 bits with 8 bytes, 55 with none). The bound of Davis, Burns,
    Bril and Lukkien, "Controller Area Network (CAN) schedulability analysis: refuted,
    revisited and revised", Real-Time Systems 35(3), 2007, eq. (2)."""
    return 55 + 10 * data_bytes


def master_sends(cob_id: int, master_id: int) -> bool:
    """Whether only a master sends frames with this COB-ID (NMT, SYNC, RPDOs, SDO requests, its
    own heartbeat): a frame the master receives with one is its own, echoed back to it."""
    if cob_id in (COB_NMT, COB_SYNC, COB_HEARTBEAT + master_id):
        return True
    node = cob_id & 0x7F
    function = cob_id & 0x780
    # RPDO 1-4 (0x200, 0x300, 0x400, 0x500 + node) and SDO requests (0x600 + node), nodes 1-127
    return node != 0 and function in (0x200, 0x300, 0x400, 0x500, 0x600)
