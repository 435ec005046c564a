"""AEC Vector Step (CANopen DS-301 V4.01 / DSP-402 V1.1): objects, codes and texts, as data.

Shared by the driver (`vendors/vector_step/`) and the simulator (`stepper_sim/vector_step/`);
no state, no I/O, no rclpy. Section names in comments are the manual's own headings
(`aec_vector_step_canopen_it.txt`, rev.09 March 2024), e.g. `# [PRE-DEFINED ERROR FIELD]`.
Texts are English renderings of the manual's Italian; the Italian original is kept beside them
where the manual gives one (`text_it`).

Addressing: DSP-402 objects sit at sub-index 0; every AEC register (0x2000-0x5FFF) is an ARRAY
whose sub 0 is the number of axes (1 on a single-axis drive) and sub 1 the value of axis 1
[INDIRIZZAMENTO REGISTRI PROPRIETARI AEC]. CANopen index = 0x2000 + Modbus address, except the
rows listed in ANOMALOUS_REGISTERS.
"""

from __future__ import annotations

import dataclasses
import os
import pathlib
from typing import Mapping

# CiA 301 numbers, re-exported (hence F401): the driver's PDO set below and the simulator use
# them as vm.*
from ...protocol.cia301 import (  # noqa: F401
    EMCY_NO_ERROR,
    PDO_COB_BASES_RX,
    PDO_COB_BASES_TX,
    PDO_INVALID,
    PDO_RTR_NOT_ALLOWED,
    RPDO_COMMUNICATION,
    RPDO_MAPPING,
    TPDO_COMMUNICATION,
    TPDO_MAPPING,
    abort_text,
    mapping_entry,
    split_mapping_entry,
)

# --- DS-301 communication objects [DS-301 V4.1 OBJECTS] ------------------------------------------
DEVICE_TYPE = 0x1000
ERROR_REGISTER = 0x1001
PRE_DEFINED_ERROR_FIELD = 0x1003
COB_ID_SYNC = 0x1005
COMMUNICATION_CYCLE_PERIOD = 0x1006
MANUFACTURER_DEVICE_NAME = 0x1008
MANUFACTURER_HARDWARE_VERSION = 0x1009
MANUFACTURER_SOFTWARE_VERSION = 0x100A
GUARD_TIME = 0x100C
LIFE_TIME_FACTOR = 0x100D
COB_ID_EMCY = 0x1014
INHIBIT_TIME_EMCY = 0x1015
CONSUMER_HEARTBEAT_TIME = 0x1016
PRODUCER_HEARTBEAT_TIME = 0x1017
IDENTITY_OBJECT = 0x1018
SDO1_PARAMETER = 0x1200

# --- DSP-402 objects [DSP-402 V1.1 OBJECTS -> TAVOLA RIASSUNTIVA] --------------------------------
ERROR_CODE = 0x603F
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
QUICK_STOP_OPTION_CODE = 0x605A
SHUTDOWN_OPTION_CODE = 0x605B
DISABLE_OPERATION_OPTION_CODE = 0x605C
STOP_OPTION_CODE = 0x605D
FAULT_REACTION_OPTION_CODE = 0x605E
MODES_OF_OPERATION = 0x6060
MODES_OF_OPERATION_DISPLAY = 0x6061
POSITION_ACTUAL_VALUE = 0x6064
VELOCITY_ACTUAL_VALUE = 0x606C
TARGET_POSITION = 0x607A
HOME_OFFSET = 0x607C                # [HOME OFFSET]: the position forced after homing
PROFILE_VELOCITY = 0x6081
END_VELOCITY = 0x6082
PROFILE_ACCELERATION = 0x6083
PROFILE_DECELERATION = 0x6084
QUICK_STOP_DECELERATION = 0x6085
MOTION_PROFILE_TYPE = 0x6086
HOMING_METHOD = 0x6098
HOMING_SPEEDS = 0x6099              # sub 1 search for switch, sub 2 search for zero
HOMING_ACCELERATION = 0x609A
INTERPOLATION_SUBMODE_SELECT = 0x60C0        # 0 = linear interpolation (the only one)
INTERPOLATION_DATA_RECORD = 0x60C1           # subs 1, 2: "buffer a due posizioni", steps
INTERPOLATION_TIME_PERIOD = 0x60C2           # sub 1 units 1..10, sub 2 index 0xFD (10^-3 s)
INTERPOLATION_SYNC_DEFINITION = 0x60C3
INTERPOLATION_DATA_CONFIGURATION = 0x60C4    # sub 2 actual size, sub 6 buffer clear/enable
DIGITAL_INPUTS = 0x60FD
DIGITAL_OUTPUTS = 0x60FE
MOTOR_TYPE = 0x6402
SUPPORTED_DRIVE_MODES = 0x6502
DRIVE_MANUFACTURER = 0x6504
HTTP_DRIVE_CATALOG_ADDRESS = 0x6505

# --- AEC object and registers [LETTURA E SCRITTURA VARIABILI], [REGISTRI PROPRIETARI] -----------
READ_WRITE_VARIABLE = 0x23E8
RPOSACT = 0x2000                    # Modbus 0000-1, actual (real) position, steps
RPOSACTREQ = 0x2004                 # 0004-5, theoretical position
RHMAXSPC = 0x2020                   # 0032-33, maximum travel during home, steps (SAVE)
RHPOS = 0x2026                      # 0038-39, position forced after homing (SAVE)
RTESTINTMOT = 0x202A                # 0042-43, fixed 1234567890
RCMDWR = 0x203B                     # 0059, command register (write only, self-clearing)
RCMDRD = 0x203D                     # 0061, command register read-back
RVELACT = 0x204B                    # 0075-76, actual velocity, rps x100
RHMODE = 0x2052                     # 0082, homing method (same numbers as 0x6098)
RCANBAUD = 0x20A9                   # 0169, CAN bit rate code (SAVE)
RCANADDR = 0x20AA                   # 0170, node-ID offset (SAVE)
RCANSTS = 0x20B8                    # 0184, CANopen LED state
RLOADSAV = 0x20C2                   # 0194, EEPROM load/save command
REEPSTS = 0x20C4                    # 0196, EEPROM status
RROTSW = 0x20C5                     # 0197, rotary switches
RSTSFLG = 0x20C7                    # 0199, status flags
RSTSFLG1 = 0x20C8                   # 0200, status flags 1
RHSTS = 0x20CA                      # 0202, homing error code
RSTRTMODE = 0x20D8                  # 0216, power-on mode (SAVE)
RALARM = 0x20E3                     # 0227, alarms (write 0 to reset)
RWARNING = 0x20E4                   # 0228, warnings
RALMCNT = 0x20ED                    # 0237, fault counter
RSTPRES = 0x210E                    # 0270, step resolution (SAVE)
RCANMODEOFOPERATION = 0x2162        # 0354, copy of 0x6060
RSTRMODEOFOPERATION = 0x2166        # 0358, power-on value of 0x6060 (SAVE)
RALARM32 = 0x222F                   # 0559-60, alarms 32 bit
RWARNING32 = 0x2231                 # 0561-62, warnings 32 bit
RALARMREACT = 0x471E                # 10014, reaction to an alarm (SAVE)
RALMBUFFRES = 0x4800                # 10144, printed 0x4800 (0x2000 + 10144 = 0x47A0)

AEC_SUB = 1                          # single-axis drive: the value of axis 1 is at sub 1

# Rows whose printed CAN index breaks "0x2000 + Modbus address" [ALLARMI E WARNING], [VARIE]:
# (printed index or text, Modbus address, name, index by the rule). The EDS and the simulator use
# the printed index; the driver does not depend on these rows.
ANOMALOUS_REGISTERS: tuple[tuple[str, str, str, int], ...] = (
    ('0x4800', '10144', 'Ralmbuffres', 0x47A0),
    ('0x4801', '10145', 'Ralmbuffptr', 0x47A1),
    ('0x4802', '10146-47', 'Ralmbufftime', 0x47A2),
    ('0x4803', '10148-49', 'Ralmbuffcode', 0x47A4),
    ('0x4807', '10151', 'Rstepout-time', 0x47A7),
    ('0x4808', '10152-53', 'Rstepout-count', 0x47A8),
    ('0x20A', '0166', 'Rprofists', 0x20A6),
)

# --- Identity and constants [DEVICE TYPE], [IDENTITY OBJECT], [SUPPORTED DRIVE MODE] -------------
DEVICE_TYPE_VALUE = 0x00040192       # DS402 profile, drive type 0x04 stepper
DEVICE_PROFILE_DS402 = 0x0192
VENDOR_ID_AEC = 0x000000BC
# Rcanbaud (0x20A9) codes 0..7 and their bit rates [bit/s]: the rates a Vector Step can run at
BITRATES = (10000, 20000, 50000, 125000, 250000, 500000, 800000, 1000000)
PRODUCT_CODES = {0x0000138E: 'SMD5006', 0x00000BBE: 'SMD3006'}
SUPPORTED_DRIVE_MODES_VALUE = 0x00010021   # bits 0 PP, 5 homing, 16 AEC velocity (not bit 6)
RTESTINTMOT_VALUE = 1234567890              # 0x499602D2

# --- Modes of operation [MODES OF OPERATION] -----------------------------------------------------
MODE_JOG = -1                        # "AEC Velocity mode (JOG)"
MODE_PROFILE_POSITION = 1
MODE_HOMING = 6
MODE_INTERPOLATED = 7
MODES = (MODE_JOG, MODE_PROFILE_POSITION, MODE_HOMING, MODE_INTERPOLATED)
MODE_NAMES: Mapping[int, str] = {
    MODE_JOG: 'AEC VELOCITY (JOG)', MODE_PROFILE_POSITION: 'PROFILE POSITION',
    MODE_HOMING: 'HOMING', MODE_INTERPOLATED: 'INTERPOLATED POSITION',
}

# --- Controlword / statusword bits specific to this drive [CONTROLWORD], [STATUSWORD] -----------
# (the CiA 402 state bits come from stepper_drivers.profiles.cia402.state_machine)
CW_BIT_JOG_START = 1 << 4            # JOG: 1 = start, 0 = stop (a level, not an edge)
CW_BIT_JOG_CCW = 1 << 5              # JOG: 0 = CW, 1 = CCW
CW_BIT_JOG_SPEED_CONTINUOUS = 1 << 6  # JOG: 1 = speed updated continuously
CW_BIT_HOMING_START = 1 << 4         # homing: rising edge starts
SW_BIT_MOTOR_MOVING = 1 << 8         # manufacturer use of bit 8 ("Motor moving")
SW_BIT_HOMING_ATTAINED = 1 << 12     # homing: "Home eseguito"
SW_BIT_HOMING_ERROR = 1 << 13        # homing: "Errore in azzeramento"
SW_BIT_JOG_STOPPED = 1 << 12         # JOG: "1 = Motore fermo"
# Interpolated position (7): the manual's CW/SW tables have no IP column; these are CiA 402's.
CW_BIT_IP_ENABLE = 1 << 4            # IP: 1 = enable interpolation (CiA 402 "enable ip mode")
SW_BIT_IP_ACTIVE = 1 << 12           # IP: 1 = interpolation active (CiA 402 "ip mode active")

# --- Interpolated position mode [INTERPOLATION SUBMODE SELECT] .. [INTERPOLATION DATA CONFIG.] --
IP_SUBMODE_LINEAR = 0
IP_BUFFER_SIZE = 2                   # 0x60C4:01 max_buffer_size
IP_TIME_INDEX_MS = 0xFD              # 0x60C2:02, the only value: 10^-3 s (UNSIGNED8 for -3)
IP_PERIOD_UNITS = (1, 10)            # 0x60C2:01 range: 1..10 ms
IP_BUFFER_CLEAR, IP_BUFFER_ENABLE = 0, 1     # 0x60C4:06 values

# --- Homing methods [HOMING METHOD] (0x6098, also Rhmode 0x2052) ---------------------------------
# Every method resets the position and sets the homed flag ("Reset quota: Si, Flag Sincro: Si").
HOMING_METHODS: Mapping[int, str] = {
    -16: 'home on FLS + motor encoder TOP, positive direction',
    -15: 'home on FLS + motor encoder TOP, negative direction',
    -14: 'home on FLS, positive direction',
    -13: 'home on FLS, negative direction',
    -12: 'home on hard stop forward + motor encoder TOP (SmartMode or closed loop only)',
    -11: 'home on hard stop backward + motor encoder TOP (SmartMode or closed loop only)',
    -10: 'home on hard stop forward (SmartMode or closed loop only)',
    -9: 'home on hard stop backward (SmartMode or closed loop only)',
    -8: 'home on hard stop forward + axis measurement (SmartMode or closed loop only)',
    -7: 'home on hard stop backward + axis measurement (SmartMode or closed loop only)',
    -6: 'home on TOP only, positive direction',
    -5: 'home on TOP only, negative direction',
    -4: 'home on BLS + motor encoder TOP, positive direction',
    -3: 'home on BLS + motor encoder TOP, negative direction',
    -2: 'home on BLS, positive direction',
    -1: 'home on BLS, negative direction',
    0: 'home on the spot (current position)',
    35: 'home on the spot (CANopen only, DS402 compatibility)',
    37: 'home on the spot (CANopen only, DS402 compatibility)',
}
HOMING_METHODS_TEXT = '-16..0, 35, 37'
HARD_STOP_METHODS = (-12, -11, -10, -9, -8, -7)

# --- Units [PROFILE VELOCITY], [PROFILE ACCELERATION] --------------------------------------------
# Velocity in rps x100 (0.01 rev/s), acceleration in rps^2 x10 (0.1 rev/s^2), position in steps.


def rps100_from_hz(velocity_steps_s: float, steps_per_rev: float) -> int:
    return int(round(velocity_steps_s / steps_per_rev * 100.0))


def hz_from_rps100(value: int, steps_per_rev: float) -> float:
    return value * steps_per_rev / 100.0


def rps2x10_from_hz_s(acceleration_steps_s2: float, steps_per_rev: float) -> int:
    return int(round(acceleration_steps_s2 / steps_per_rev * 10.0))


def hz_s_from_rps2x10(value: int, steps_per_rev: float) -> float:
    return value * steps_per_rev / 10.0


# --- Objects the driver touches (checked against the EDS by test_vector_step_eds.py) -------------
@dataclasses.dataclass(frozen=True)
class Obj:
    index: int
    sub: int
    name: str
    data_type: str          # u8 i8 u16 i16 u32 i32 str
    access: str             # ro wo rw const
    pdo: str = ''           # 'T' TxPDO-mappable, 'R' RxPDO-mappable, '' not used in a PDO

    def __str__(self) -> str:
        return f'0x{self.index:04X}:{self.sub:02X} {self.name}'


DRIVER_OBJECTS: tuple[Obj, ...] = (
    Obj(DEVICE_TYPE, 0, 'Device Type', 'u32', 'ro'),
    Obj(ERROR_REGISTER, 0, 'Error Register', 'u8', 'ro'),
    Obj(PRE_DEFINED_ERROR_FIELD, 0, 'number_of_errors', 'u8', 'rw'),
    Obj(PRE_DEFINED_ERROR_FIELD, 1, 'standard_error_field', 'u32', 'ro'),
    Obj(MANUFACTURER_DEVICE_NAME, 0, 'Manufacturer Device Name', 'str', 'const'),
    Obj(MANUFACTURER_SOFTWARE_VERSION, 0, 'Manufacturer Software Version', 'str', 'const'),
    Obj(COMMUNICATION_CYCLE_PERIOD, 0, 'Communication Cycle Period', 'u32', 'rw'),
    Obj(CONSUMER_HEARTBEAT_TIME, 1, 'Consumer_heartbeat_time', 'u32', 'rw'),
    Obj(PRODUCER_HEARTBEAT_TIME, 0, 'Producer Heartbeat Time', 'u16', 'rw'),
    Obj(IDENTITY_OBJECT, 1, 'vendor_ID', 'u32', 'ro'),
    Obj(IDENTITY_OBJECT, 2, 'product_code', 'u32', 'ro'),
    Obj(IDENTITY_OBJECT, 3, 'revision_number', 'u32', 'ro'),
    Obj(IDENTITY_OBJECT, 4, 'serial_number', 'u32', 'ro'),
    *(Obj(RPDO_COMMUNICATION + n, s, f'RxPDO{n + 1} {what}', t, 'rw')
      for n in range(4) for s, what, t in ((1, 'COB-ID', 'u32'), (2, 'transmission type', 'u8'))),
    *(Obj(TPDO_COMMUNICATION + n, s, f'TxPDO{n + 1} {what}', t, 'rw')
      for n in range(4) for s, what, t in ((1, 'COB-ID', 'u32'), (2, 'transmission type', 'u8'),
                                           (3, 'inhibit time', 'u16'), (5, 'event timer', 'u16'))),
    *(Obj(base + n, s, f'{kind}PDO{n + 1} mapping {s}', 'u8' if s == 0 else 'u32', 'rw')
      for base, kind in ((RPDO_MAPPING, 'Rx'), (TPDO_MAPPING, 'Tx')) for n in range(4)
      for s in range(0, 9)),
    Obj(ERROR_CODE, 0, 'Error code', 'u16', 'ro'),
    Obj(CONTROLWORD, 0, 'Controlword', 'u16', 'rw', 'R'),
    Obj(STATUSWORD, 0, 'Statusword', 'u16', 'ro', 'T'),
    Obj(MODES_OF_OPERATION, 0, 'Modes of operation', 'i8', 'wo', 'R'),
    Obj(MODES_OF_OPERATION_DISPLAY, 0, 'Modes of operation display', 'i8', 'ro', 'T'),
    Obj(POSITION_ACTUAL_VALUE, 0, 'Position actual value', 'i32', 'ro', 'T'),
    Obj(VELOCITY_ACTUAL_VALUE, 0, 'Velocity actual value', 'i32', 'ro', 'T'),
    Obj(TARGET_POSITION, 0, 'Target position', 'i32', 'rw', 'R'),
    Obj(HOME_OFFSET, 0, 'Home offset', 'i32', 'rw'),
    Obj(PROFILE_VELOCITY, 0, 'Profile velocity', 'u32', 'rw', 'R'),
    Obj(END_VELOCITY, 0, 'End velocity', 'u32', 'rw'),
    Obj(PROFILE_ACCELERATION, 0, 'Profile acceleration', 'u32', 'rw'),
    Obj(PROFILE_DECELERATION, 0, 'Profile deceleration', 'u32', 'rw'),
    Obj(HOMING_METHOD, 0, 'Homing method', 'i8', 'rw'),
    Obj(HOMING_SPEEDS, 1, 'Speed during search for switch', 'u32', 'rw'),
    Obj(HOMING_SPEEDS, 2, 'Speed during search for zero', 'u32', 'rw'),
    Obj(HOMING_ACCELERATION, 0, 'Homing acceleration', 'u32', 'rw'),
    Obj(INTERPOLATION_SUBMODE_SELECT, 0, 'Interpolation sub mode select', 'i16', 'rw'),
    Obj(INTERPOLATION_DATA_RECORD, 1, '1st_ip_function_parameter', 'i32', 'rw', 'R'),
    Obj(INTERPOLATION_DATA_RECORD, 2, '2nd_ip_function_parameter', 'i32', 'rw', 'R'),
    Obj(INTERPOLATION_TIME_PERIOD, 1, 'ip_time_units', 'u8', 'rw'),
    Obj(INTERPOLATION_TIME_PERIOD, 2, 'ip_time_index', 'u8', 'rw'),
    Obj(SUPPORTED_DRIVE_MODES, 0, 'Supported drive modes', 'u32', 'ro'),
    Obj(RCMDWR, AEC_SUB, 'Rcmdwr', 'u16', 'wo'),
    Obj(RLOADSAV, AEC_SUB, 'Rloadsav', 'u16', 'rw'),
    Obj(REEPSTS, AEC_SUB, 'Reepsts', 'u16', 'ro'),
    Obj(RSTSFLG, AEC_SUB, 'Rstsflg', 'u16', 'rw', 'T'),
    Obj(RSTSFLG1, AEC_SUB, 'Rstsflg1', 'u16', 'ro'),
    Obj(RHSTS, AEC_SUB, 'Rhsts', 'u16', 'ro'),
    Obj(RALARM, AEC_SUB, 'Ralarm', 'u16', 'rw'),
    Obj(RWARNING, AEC_SUB, 'Rwarning', 'u16', 'ro'),
    Obj(RSTPRES, AEC_SUB, 'Rstpres', 'u16', 'rw'),
    Obj(RALARM32, AEC_SUB, 'Ralarm32', 'u32', 'rw'),
)

# --- The driver's PDO set, written at every boot [COME MAPPARE UN PDO] --------------------------
# (object, sub, bits). The statusword is first in every TxPDO and the controlword first in every
# RxPDO: [STATUSWORD]/[CONTROLWORD] say they "are always mapped in the first two bytes".
DRIVER_RPDOS: tuple[tuple[tuple[int, int, int], ...], ...] = (
    ((CONTROLWORD, 0, 16), (MODES_OF_OPERATION, 0, 8)),        # RxPDO1 (= manual default)
    ((CONTROLWORD, 0, 16), (TARGET_POSITION, 0, 32)),          # RxPDO2 (= manual default)
    ((CONTROLWORD, 0, 16), (PROFILE_VELOCITY, 0, 32)),         # RxPDO3: JOG start + speed
    # RxPDO4: one interpolation point per SYNC period (0x60C1 is "WMAP" [TAVOLA RIASSUNTIVA])
    ((CONTROLWORD, 0, 16), (INTERPOLATION_DATA_RECORD, 1, 32)),
)
DRIVER_TPDOS: tuple[tuple[tuple[int, int, int], ...], ...] = (
    ((STATUSWORD, 0, 16), (MODES_OF_OPERATION_DISPLAY, 0, 8)),  # TxPDO1 (= manual default)
    ((STATUSWORD, 0, 16), (POSITION_ACTUAL_VALUE, 0, 32)),      # TxPDO2 (= manual default)
    ((STATUSWORD, 0, 16), (VELOCITY_ACTUAL_VALUE, 0, 32)),      # TxPDO3
    ((STATUSWORD, 0, 16), (RSTSFLG, AEC_SUB, 16), (ERROR_REGISTER, 0, 8)),   # TxPDO4
)

# Manual defaults [RxPDO/TxPDO MAPPING PARAMETERS]: "x - -" = none.
DEFAULT_RPDO_MAPPING = ((0x60400010, 0x60600008), (0x60400010, 0x607A0020), (), ())
DEFAULT_TPDO_MAPPING = ((0x60410010, 0x60610008), (0x60410010, 0x60640020), (), ())
DEFAULT_TRANSMISSION_TYPE = 0xFE


# --- EMCY codes [PRE-DEFINED ERROR FIELD] -----------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Emcy:
    code: int
    text: str
    text_it: str


EMCY_CODES: Mapping[int, Emcy] = {e.code: e for e in (
    Emcy(0x0000, 'generic error (CiA 301: error reset / no error)', 'Errore generico'),
    Emcy(0x5400, 'error in the power stage of the drive',
         "Errore nello stadio di potenza dell'azionamento"),
    Emcy(0x8110, 'bus overload (message lost)', 'Sovraccarico del bus (Messaggio perso)'),
    Emcy(0x8120, 'CAN controller in "Error passive" state (CAN controller disabled)',
         'CAN controller in "Error passive" state (CAN controller disabilitato)'),
    Emcy(0x8130, 'error in message control (node guarding / heartbeat)',
         'Errore nel controllo del messaggio'),
    Emcy(0x8140, 'recovered from bus off', 'Uscita dallo stato Bus off'),
    Emcy(0x8150, 'COB-ID collision', 'Collisione COB-ID'),
    Emcy(0x8210, 'PDO length greater than the mapped value',
         'Lunghezza PDO maggiore del valore mappato'),
    Emcy(0x8220, 'PDO length less than the mapped value',
         'Lunghezza PDO inferiore del valore mappato'),
    Emcy(0xFF01, 'NVRAM read/write error (error code: Reepsts)',
         'Errore in lettura/scrittura della memoria NVRAM + Codice errore (Reepsts)'),
    Emcy(0xFF02, 'error executing the HOME command (axis 1)',
         'Errore in esecuzione del comando HOME (per SMD2204 - asse 1)'),
    Emcy(0xFF03, 'interpolation mode: no data to process',
         'Mancanza dati da elaborare in modalita interpolazione'),
    Emcy(0xFF04, 'interpolation alarm: SYNC too early',
         'Allarme interpolazione: Sync troppo in anticipo'),
    Emcy(0xFF05, 'interpolation alarm: SYNC too late',
         'Allarme interpolazione: Sync troppo in ritardo'),
    Emcy(0xFF06, 'error executing the HOME command (axis 2)',
         'Errore in esecuzione del comando HOME (solo per SMD2204 - asse 2)'),
    Emcy(0xFF07, 'error executing the HOME command (axis 3)',
         'Errore in esecuzione del comando HOME (solo per SMD2204 - asse 3)'),
    Emcy(0xFF13, 'power stage error, axis 1 (multi-axis drive)',
         "Errore nello stadio di potenza dell'azionamento per l'asse 1"),
    Emcy(0xFF14, 'power stage error, axis 2 (multi-axis drive)',
         "Errore nello stadio di potenza dell'azionamento per l'asse 2"),
    Emcy(0xFF15, 'power stage error, axis 3 (multi-axis drive)',
         "Errore nello stadio di potenza dell'azionamento per l'asse 3"),
)}
EMCY_POWER_STAGE = 0x5400
EMCY_ERROR_CONTROL = 0x8130
EMCY_PDO_TOO_LONG = 0x8210
EMCY_PDO_TOO_SHORT = 0x8220
EMCY_NVRAM = 0xFF01
EMCY_HOME_ERROR = 0xFF02
EMCY_IP_NO_DATA = 0xFF03             # interpolation buffer empty at a SYNC (underflow)
EMCY_IP_SYNC_EARLY = 0xFF04
EMCY_IP_SYNC_LATE = 0xFF05
IP_EMCY_CODES = (EMCY_IP_NO_DATA, EMCY_IP_SYNC_EARLY, EMCY_IP_SYNC_LATE)
IP_EMCY_DATA = b'\x01\x00'           # "VSD[0]==1, VSD[1]==0 fissi"
HOME_ERROR_CODES = (0xFF02, 0xFF06, 0xFF07)

# 0x1001 bits [ERROR REGISTER]
ERROR_REGISTER_GENERIC = 1 << 0
ERROR_REGISTER_COMMUNICATION = 1 << 4
ERROR_REGISTER_DEVICE_PROFILE = 1 << 5
ERROR_HISTORY_DEPTH = 2              # "fino a 2 errori"


# --- Register bit texts --------------------------------------------------------------------------
RALARM_BITS: Mapping[int, str] = {          # Ralarm 0x20E3 / Ralarm32 0x222F [ALLARMI E WARNING]
    0: 'overcurrent HW', 1: 'overcurrent SW', 2: 'I2T', 3: 'position error',
    4: 'following error', 5: 'digital output overload', 6: 'over-temperature',
    7: 'over-voltage', 8: 'under-voltage', 9: 'motor encoder phasing error',
    10: 'phase A disconnected', 11: 'phase B disconnected', 12: 'positioning timeout',
    13: 'homing error', 14: 'encoder inverted in Smart Mode or closed loop',
    15: 'encoder fault', 18: 'missing SYNC (CANopen or EtherCAT)',
    19: 'SSP fault (inconsistent inputs)', 20: 'VLogic under-voltage',
    21: 'STO fault (test on STO A failed)', 22: 'STO fault (test on STO B failed)',
    23: 'fault on the "drive in safety" output pin',
}
# Alarms the manual marks "non mascherabile" that stop the power stage at once: the simulator's
# reaction for Ralarmreact -4 ("abort on emergency ramp and current off depending on the alarm").
RALARM_IMMEDIATE_BITS = (0, 1, 5, 6, 7, 9, 10, 11)
RWARNING_BITS: Mapping[int, str] = {        # Rwarning 0x20E4
    0: 'overcurrent HW', 1: 'overcurrent SW', 2: 'I2T', 3: 'position error',
    4: 'following error', 5: 'digital output overload', 6: 'over-temperature',
    7: 'over-voltage', 8: 'under-voltage', 9: 'current limited by voltage',
    10: 'regulator saturated', 11: 'current limit active', 12: 'positioning timeout',
}
RHSTS_BITS: Mapping[int, str] = {           # Rhsts 0x20CA [ISTRUZIONE HOME]
    0: 'home in progress', 1: 'drive not enabled', 2: 'maximum travel for home exceeded',
    3: 'BLS error', 4: 'FLS error', 5: 'home interrupted', 6: 'unknown home error',
    7: 'hard-stop home with FOC_OPEN',
}
RHSTS_IN_PROGRESS = 1 << 0
RHSTS_NOT_ENABLED = 1 << 1
RHSTS_MAX_TRAVEL = 1 << 2
RHSTS_BLS = 1 << 3
RHSTS_FLS = 1 << 4
RHSTS_INTERRUPTED = 1 << 5
RHSTS_UNKNOWN = 1 << 6
RHSTS_FOC_OPEN = 1 << 7
REEPSTS_BITS: Mapping[int, str] = {         # Reepsts 0x20C4 [GESTIONE MEMORIA NON VOLATILE]
    0: 'R/W in progress', 1: 'invalid command', 2: 'register read error',
    3: 'register write error', 4: 'variable read error', 5: 'variable write error',
    6: 'program read error', 7: 'program write error', 8: 'password read error',
    9: 'password write error', 10: 'task read error', 11: 'task write error',
    12: 'alarm buffer read error', 13: 'alarm buffer write error',
    14: 'current sensor offset read error', 15: 'current sensor offset write error',
}
REEPSTS_BUSY = 1 << 0
REEPSTS_INVALID_COMMAND = 1 << 1
RSTSFLG_ENABLED = 1 << 0
RSTSFLG_ALARM = 1 << 1
RSTSFLG_HOMED = 1 << 2               # "Asse azzerato"
RSTSFLG_MOVING = 1 << 3
RSTSFLG_HOME_ERROR = 1 << 8
RSTSFLG_CURRENT_ON = 1 << 9
RSTSFLG_IN_POSITION = 1 << 10
RSTSFLG_HOME_IN_PROGRESS = 1 << 15
RSTSFLG1_STO = 1 << 15               # Rstsflg1 b15 "STO attivo"
RSTSFLG1_POWER_OFF = 1 << 2          # b2 "Power_OFF signal"
RCMDWR_BITS: Mapping[int, str] = {          # Rcmdwr 0x203B [COMANDI MOVIMENTO]
    0: 'DISABLE DRIVE', 1: 'ENABLE DRIVE', 2: 'ABORT', 3: 'STOP', 4: 'ESTOP', 5: 'JOG CW',
    6: 'JOG CCW', 7: 'new setpoint GO', 8: 'new setpoint GOR', 9: 'HOME', 10: 'GEAR',
    11: 'CAM start/stop', 12: 'CAM', 13: 'TASK', 14: 'BESTOP', 15: 'SHIFT STOP',
}
RCMDWR_ABORT = 1 << 2                # stop on the emergency ramp
RCMDWR_STOP = 1 << 3                 # stop on the ramp (0x605D stop option code)

# Rloadsav 0x20C2 commands; the register "is reset to 0 when the command has been executed".
RLOADSAV_LOAD_REGISTERS = 0x01
RLOADSAV_SAVE_REGISTERS = 0x81
RLOADSAV_RESET_REGISTERS = 0x84
RLOADSAV_RESTART = (0x8E, 0x8F)      # "142-143 = restart, written consecutively"

# --- SDO abort codes (CiA 301; the manual names the first five; texts: cia301.abort_text) --
ABORT_NOT_READABLE = 0x06010001
ABORT_READ_ONLY = 0x06010002
ABORT_NO_OBJECT = 0x06020000
ABORT_NOT_MAPPABLE = 0x06040041
ABORT_PDO_TOO_LONG = 0x06040042
ABORT_PARAMETER_INCOMPATIBLE = 0x06040043
ABORT_LENGTH = 0x06070010
ABORT_NO_SUBINDEX = 0x06090011
ABORT_VALUE_RANGE = 0x06090030
ABORT_DEVICE_STATE = 0x08000022
ABORT_NO_DATA = 0x08000024


def emcy_text(code: int, vendor_data: bytes = b'') -> str:
    """The manual's text for an EMCY code, with the vendor bytes decoded where it says how."""
    entry = EMCY_CODES.get(code)
    if entry is None and code & 0xFF00 == 0xFF00:
        text = f'manufacturer-specific error 0x{code:04X}'
    elif entry is None:
        text = f"error 0x{code:04X} (not in the manual's EMCY table)"
    else:
        text = entry.text
    if code in HOME_ERROR_CODES and vendor_data:
        rhsts = vendor_data[0]
        bits = [RHSTS_BITS[b] for b in sorted(RHSTS_BITS) if rhsts & (1 << b)]
        text += f': {", ".join(bits) or "no Rhsts bit"} (Rhsts 0x{rhsts:02X})'
    elif code == EMCY_NVRAM and len(vendor_data) >= 2:
        reepsts = int.from_bytes(vendor_data[:2], 'little')
        text += f': {bit_texts(reepsts, REEPSTS_BITS) or "-"} (Reepsts 0x{reepsts:04X})'
    return text


def bit_texts(value: int, table: Mapping[int, str]) -> str:
    return ', '.join(table.get(b, f'bit {b}') for b in range(32) if value & (1 << b))


EDS_FILE = 'config/vector_step.eds'     # relative to the package share dir and the source tree


def eds_path() -> pathlib.Path:
    """config/vector_step.eds of the source tree (tests, tools, a --symlink-install). A node
    finds the installed one through ROS (ros/entry_points.py) and passes it in as can.eds_file:
    this module does not import ROS."""
    here = pathlib.Path(os.path.realpath(__file__)).parents[3]   # src/stepper_drivers
    for candidate in (here / EDS_FILE, here.parents[1] / EDS_FILE):
        if candidate.exists():
            return candidate
    raise FileNotFoundError(f'{EDS_FILE} not found in the source tree: set can.eds_file')
