"""The real `xplus_mt_sim` executable: ready line, ROS services and topic, Modbus, SIGINT -> 0."""

import pathlib
import signal
import subprocess
import time

from pymodbus.client import ModbusTcpClient
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from std_msgs.msg import Float64
from stepper_drivers_msgs.srv import InjectFault, SetInput
from stepper_sim.harness import Proc, free_port

WS = pathlib.Path(__file__).resolve().parents[4]
EXE = WS / 'install' / 'stepper_sim' / 'lib' / 'stepper_sim' / 'xplus_mt_sim'
PARAMS = WS / 'config' / 'xplus_mt_sim.yaml'


@pytest.fixture
def ros():
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('xplus_mt_sim_test_client', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    yield node, executor
    executor.shutdown()
    node.destroy_node()
    rclpy.shutdown(context=context)


def call(node, executor, srv_type, name, request):
    client = node.create_client(srv_type, name)
    assert client.wait_for_service(timeout_sec=15.0), f'service {name} not available'
    future = client.call_async(request)
    executor.spin_until_future_complete(future, timeout_sec=10.0)
    assert future.done(), f'no answer from {name}'
    return future.result()


def test_executable_ready_services_modbus_and_sigint(ros, tmp_path):
    if not EXE.exists():
        pytest.fail(f'{EXE} missing: run scripts/bootstrap.sh')
    node, executor = ros
    port = free_port()
    sim = Proc([str(EXE), '--ros-args', '--params-file', str(PARAMS), '-p', f'port:={port}'],
               tmp_path, 'xplus_mt_sim')
    try:
        sim.wait_line(f'xplus_mt_sim: ready on 127.0.0.1:{port}', 20.0)
        mb = ModbusTcpClient('127.0.0.1', port=port, timeout=1.0, retries=0)
        assert mb.connect()
        assert mb.read_holding_registers(1001, count=1, device_id=1).registers == [0x0270]
        # the shipped simulator is a factory drive: Input Config 15, every input general purpose
        assert mb.read_holding_registers(1088, count=1, device_id=1).registers == [15]

        positions = []
        node.create_subscription(Float64, '/xplus_mt_sim/axis1/true_position_steps',
                                 lambda msg: positions.append(msg.data), 10)
        deadline = time.monotonic() + 10.0
        while not positions and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.1)
        assert positions and positions[-1] == 0.0

        request = InjectFault.Request(drive='axis1', kind='drive_fault', code=0x4310)
        response = call(node, executor, InjectFault, '/xplus_mt_sim/inject_fault', request)
        assert response.success, response.message
        assert 'excessive temperature' in response.message
        assert mb.read_holding_registers(1001, count=1, device_id=1).registers == [0x0218]
        assert mb.read_holding_registers(1006, count=2, device_id=1).registers == [1, 0x4310]
        assert mb.read_holding_registers(1001, count=1, device_id=2).registers == [0x0270]

        response = call(node, executor, InjectFault, '/xplus_mt_sim/inject_fault',
                        InjectFault.Request(drive='axis1', kind='melt'))
        assert not response.success and 'drive_fault' in response.message

        response = call(node, executor, SetInput, '/xplus_mt_sim/set_input',
                        SetInput.Request(drive='axis2', input='home', value=True))
        assert response.success, response.message
        di = mb.read_holding_registers(1008, count=2, device_id=2).registers
        assert di[0] & 0x0004 and di[1] & 0x0001          # PX (bit 2) and I0 (bit 16)
        mb.close()

        assert sim.stop(signal.SIGINT, timeout_s=15) == 0
    finally:
        sim.kill()


def test_bad_parameter_names_itself():
    if not EXE.exists():
        pytest.fail(f'{EXE} missing: run scripts/bootstrap.sh')
    result = subprocess.run([str(EXE), '--ros-args', '-p', 'port:=70000'], capture_output=True,
                            text=True, timeout=30, cwd=WS)
    assert result.returncode == 2              # sim_node: a bad parameter exits 2
    assert 'parameter port: 70000 not in 0..65535' in result.stderr
