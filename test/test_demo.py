"""The README's main command: scripts/demo.py runs every vendor, writes the plot, leaves nothing.

The demo runs as a subprocess with a marker in its environment, which every process it starts
inherits; afterwards no process on the machine may carry the marker (the Vector Step node's SYNC
producer process included). The Vector Step demo also runs beside two busy loops (a user's busy
laptop, a loaded CI machine): its drives watch the node's SYNC (0x1006) and faulted "missing
SYNC" there once; STEPPER_DEMO_LOAD_RUNS=10 runs it ten times in a row.
"""

import os
import pathlib
import subprocess
import sys
import time
import uuid

import pytest
from rosharness import ROOT


def processes_with(marker: str) -> list[str]:
    found = []
    for proc in pathlib.Path('/proc').iterdir():
        if not proc.name.isdigit():
            continue
        try:
            if marker.encode() in (proc / 'environ').read_bytes():
                found.append(f"{proc.name}: {(proc / 'cmdline').read_bytes()[:120]!r}")
        except OSError:          # gone meanwhile, or not ours to read
            continue
    return found


def test_demo_moves_every_drive_plots_and_cleans_up(tmp_path):
    marker = f'STEPPER_DEMO_TEST_{uuid.uuid4().hex}'
    plot = tmp_path / 'positions.png'
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, str(ROOT / 'scripts' / 'demo.py'), '--plot', str(plot)],
                       capture_output=True, text=True, timeout=150,
                       env={**os.environ, marker: '1'})
    took = time.monotonic() - t0
    assert r.returncode == 0, f'{r.stderr[-3000:]}\n{r.stdout[-3000:]}'
    assert 'demo OK' in r.stdout
    assert took < 110, f'the demo took {took:.0f} s (the README promises under two minutes)'
    for vendor in ('xplus_mt', 'rd4', 'xmind_k', 'vector_step'):
        assert f'[{vendor}] simulator and node up' in r.stdout
    assert r.stdout.count('stopped by the watchdog') == 9          # 2 + 2 + 3 + 2 drives
    assert 'DRIVE' in r.stdout and 'vector_step_node/axis2' in r.stdout   # the status table
    assert r.stdout.count('trajectory done: every joint reached its goal') == 4   # per bus
    for png in (plot, tmp_path / 'positions_paths.png'):
        data = png.read_bytes()
        assert data[:8] == b'\x89PNG\r\n\x1a\n' and len(data) > 20_000
    assert processes_with(marker) == []


LOAD_RUNS = int(os.environ.get('STEPPER_DEMO_LOAD_RUNS', '1'))


@pytest.mark.parametrize('run', range(LOAD_RUNS))
def test_the_vector_step_demo_passes_beside_two_busy_loops(run, tmp_path):
    marker = f'STEPPER_DEMO_TEST_{uuid.uuid4().hex}'
    loops = [subprocess.Popen([sys.executable, '-c', 'while True: pass']) for _ in range(2)]
    try:
        r = subprocess.run([sys.executable, str(ROOT / 'scripts' / 'demo.py'),
                            '--vendor', 'vector_step', '--plot', str(tmp_path / 'p.png')],
                           capture_output=True, text=True, timeout=150,
                           env={**os.environ, marker: '1'})
    finally:
        for p in loops:
            p.kill()
            p.wait()
    assert r.returncode == 0, f'{r.stderr[-3000:]}\n{r.stdout[-3000:]}'
    assert 'demo OK' in r.stdout and 'missing SYNC' not in r.stdout
    assert processes_with(marker) == []
