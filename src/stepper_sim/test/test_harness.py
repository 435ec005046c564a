"""harness.Proc: a started process dies with the process that started it (main thread),
not with a worker thread that started it (the demo starts its processes from threads)."""

import os
import subprocess
import sys
import textwrap

from stepper_sim.harness import wait_for

STARTER = textwrap.dedent("""
    import os, pathlib, sys, tempfile, threading
    from stepper_sim.harness import Proc
    log = pathlib.Path(tempfile.mkdtemp())
    if sys.argv[1] == 'thread':
        box = []
        t = threading.Thread(target=lambda: box.append(Proc(['sleep', '30'], log, 's')))
        t.start(); t.join()
        p = box[0]
    else:
        p = Proc(['sleep', '30'], log, 's')
    print(p.pid, flush=True)
    sys.stdin.readline()                 # the test says when
    os.abort() if sys.argv[1] == 'main' else os._exit(0)
""")


def _alive(pid):
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    with open(f'/proc/{pid}/stat') as f:
        return f.read().split()[2] != 'Z'


def _start(mode):
    starter = subprocess.Popen([sys.executable, '-c', STARTER, mode], stdin=subprocess.PIPE,
                               stdout=subprocess.PIPE, text=True)
    child = int(starter.stdout.readline())
    assert _alive(child)
    return starter, child


def test_a_child_dies_when_its_starting_process_aborts():
    starter, child = _start('main')
    starter.stdin.write('\n')
    starter.stdin.flush()
    starter.wait(timeout=10)
    wait_for(lambda: not _alive(child), 10.0, 'the child killed with its parent')


def test_a_child_started_from_a_worker_thread_outlives_that_thread():
    starter, child = _start('thread')
    try:
        assert _alive(child)             # the thread that started it has ended
    finally:
        os.kill(child, 9)
        starter.stdin.write('\n')
        starter.stdin.flush()
        starter.wait(timeout=10)
