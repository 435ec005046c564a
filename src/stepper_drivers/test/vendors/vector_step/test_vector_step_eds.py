"""config/vector_step.eds: loads with canopen, and holds every object the driver touches as the
manual describes it (type, access, PDO mapping, defaults)."""

import canopen
from canopen.objectdictionary import datatypes
import pytest
from stepper_drivers.vendors.vector_step import regmap as vm

TYPES = {'u8': datatypes.UNSIGNED8, 'i8': datatypes.INTEGER8, 'u16': datatypes.UNSIGNED16,
         'i16': datatypes.INTEGER16, 'u32': datatypes.UNSIGNED32, 'i32': datatypes.INTEGER32,
         'str': datatypes.VISIBLE_STRING}


@pytest.fixture(scope='module')
def od():
    return canopen.import_od(str(vm.eds_path()), 5)


def entry(od, index, sub):
    obj = od[index]
    if isinstance(obj, canopen.objectdictionary.ODVariable):
        assert sub == 0, f'0x{index:04X} is a VAR, sub {sub} asked'
        return obj
    assert sub in obj.subindices, f'0x{index:04X}:{sub:02X} missing from the EDS'
    return obj.subindices[sub]


def test_eds_is_installed_with_the_package():
    path = vm.eds_path()
    assert path.name == 'vector_step.eds' and path.exists()
    assert 'install' in str(path) or 'config' in str(path)


@pytest.mark.parametrize('obj', vm.DRIVER_OBJECTS, ids=str)
def test_every_driver_object_has_the_manuals_type_and_access(od, obj):
    var = entry(od, obj.index, obj.sub)
    assert var.data_type == TYPES[obj.data_type], f'{obj}: data type 0x{var.data_type:04X}'
    assert var.access_type == obj.access, f'{obj}: access {var.access_type}'
    if obj.pdo:
        assert var.pdo_mappable, f'{obj} must be PDO-mappable ({obj.pdo})'


def test_driver_pdo_entries_are_mappable_in_their_direction(od):
    for pdos, readable in ((vm.DRIVER_RPDOS, False), (vm.DRIVER_TPDOS, True)):
        for pdo in pdos:
            assert pdo[0][0] == (vm.STATUSWORD if readable else vm.CONTROLWORD)
            assert sum(bits for _, _, bits in pdo) <= 64
            for index, sub, bits in pdo:
                var = entry(od, index, sub)
                assert var.pdo_mappable and len(var) == bits, (hex(index), sub)
                assert var.readable if readable else var.writable


def test_communication_defaults_follow_the_manual(od):
    assert od[vm.DEVICE_TYPE].default == 0x00040192                       # [DEVICE TYPE]
    assert od[vm.IDENTITY_OBJECT][1].default == 0xBC                      # AEC vendor ID
    assert od[vm.SUPPORTED_DRIVE_MODES].default == 0x00010021             # bit 6 not set
    assert od[vm.COB_ID_EMCY].default == 0x80 + 5                         # $NODEID+0x80
    assert od[vm.PRODUCER_HEARTBEAT_TIME].default == 0                    # heartbeat off
    assert od[vm.PRE_DEFINED_ERROR_FIELD][0].max == vm.ERROR_HISTORY_DEPTH
    assert od[vm.HTTP_DRIVE_CATALOG_ADDRESS].default == 'www.aec-smd.it'
    for n in range(4):
        assert od[vm.RPDO_COMMUNICATION + n][1].default == vm.PDO_COB_BASES_RX[n] + 5
        assert od[vm.TPDO_COMMUNICATION + n][1].default == vm.PDO_COB_BASES_TX[n] + 5
        assert od[vm.RPDO_COMMUNICATION + n][2].default == 0xFE
        assert od[vm.TPDO_COMMUNICATION + n][2].default == 0xFE
        for base, defaults in ((vm.RPDO_MAPPING, vm.DEFAULT_RPDO_MAPPING),
                               (vm.TPDO_MAPPING, vm.DEFAULT_TPDO_MAPPING)):
            mapping = od[base + n]
            assert mapping[0].default == len(defaults[n])
            assert mapping[0].access_type == 'rw'      # the mapping procedure writes sub 0
            assert [mapping[k].default for k in range(1, len(defaults[n]) + 1)] == \
                list(defaults[n])


def test_dsp402_objects_and_ranges(od):
    assert od[vm.MODES_OF_OPERATION].access_type == 'wo'                  # read 0x6061
    assert od[vm.MODES_OF_OPERATION].default == vm.MODE_PROFILE_POSITION
    assert (od[vm.HOMING_METHOD].min, od[vm.HOMING_METHOD].max) == (-16, 37)
    assert od[vm.HOMING_SPEEDS][1].default == 100 and od[vm.HOMING_SPEEDS][2].default == 10
    assert od[vm.PROFILE_ACCELERATION].max == 200000
    assert od[vm.QUICK_STOP_DECELERATION].pdo_mappable is False          # detail page: "No"
    assert od[vm.MOTOR_TYPE].default == 9                                 # "ritorna sempre a 9"
    assert 0x60FF not in od                                               # no target velocity


def test_aec_registers_are_arrays_with_the_axis_count_at_sub0(od):
    for index in (vm.RPOSACT, vm.RLOADSAV, vm.RSTSFLG, vm.RALARM32, vm.RCMDWR, vm.RALARMREACT):
        array = od[index]
        assert isinstance(array, canopen.objectdictionary.ODArray), hex(index)
        assert array[0].default == 1 and array[0].access_type == 'ro'
        assert sorted(array.subindices) == [0, 1]
    assert od[vm.RTESTINTMOT][1].default == vm.RTESTINTMOT_VALUE
    assert od[vm.RALARMREACT][1].default == -4


def test_registers_that_break_the_0x2000_rule_use_the_printed_index(od):
    for printed, modbus, name, by_rule in vm.ANOMALOUS_REGISTERS[:4]:
        assert int(printed, 16) in od, name
        assert int(printed, 16) != by_rule
        assert by_rule == 0x2000 + int(modbus.split('-')[0])
    assert 0x2000 + 194 == vm.RLOADSAV and 0x2000 + 199 == vm.RSTSFLG    # the rule elsewhere
