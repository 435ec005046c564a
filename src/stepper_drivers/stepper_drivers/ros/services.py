"""The services and actions of each drive of a DriveNode: enable, stop, home, fault_reset,
save_params, read_register, write_register, and the MoveTo and Home actions.

Each is an async callback of the node's executor: it checks the request against the drive's
latest snapshot (the node's `check_link`, `check_position`, `refuse`), enqueues a job for the
bus owner and `await`s its result, then the polls it needs, without holding an executor thread,
so one SingleThreadedExecutor serves the node and a stop is never queued behind a homing. A
service or action that changed a drive answers once the change is published (`published`).

An answer is judged only by snapshots that followed its own writes: the job's future carries
the drive's write count at its end (owner/polling.py, snapshot provenance), and a snapshot
counts for the answer only when its `after_write` is at least that (`_command`, `_since`). A
snapshot whose read went out before the command (a poll under way while it ran) is no answer
to it.
"""

from __future__ import annotations

import concurrent.futures
from typing import Any, Callable, Protocol

from rclpy.action import ActionServer, CancelResponse, GoalResponse
from std_srvs.srv import SetBool, Trigger
from stepper_drivers_msgs.action import Home, MoveTo
from stepper_drivers_msgs.srv import ReadRegister, WriteRegister

from ..contract.drive import DriveError, DriveState, HomingState, RefusedError
from ..owner import Cancelled
from ..owner.commands import Command, CommandRefused, JobKind
from .handle import DriveHandle, JobAwaiter

# Position tolerance for "target reached" in a MoveTo action, in steps.
TARGET_TOLERANCE_STEPS = 2
# A MoveTo result is decided on this many consecutive snapshots that agree (standstill).
SETTLED_POLLS = 2
# How long a service's job may wait to start: one not started by then is dropped, and the
# service answers so; one that started is awaited to its end, however long it runs.
JOB_TIMEOUT_S = 15.0


class ServiceHost(JobAwaiter, Protocol):
    """What the services need of their node (node.DriveNode): its checks
    and refusals, the awaiting of owner-thread futures, and the rclpy Node calls below."""

    srv_group: Any           # the callback group of services and actions (reentrant)
    log: Any                 # the node's logger

    def refuse(self, h: DriveHandle, why: str) -> None: ...

    def check_link(self, h: DriveHandle, what: str, safe: bool = False) -> None: ...

    def check_position(self, h: DriveHandle, what: str, position: float,
                       taken: bool = True) -> int: ...

    def create_service(self, *args: Any, **kwargs: Any) -> Any: ...

    def get_clock(self) -> Any: ...


class DriveServices:
    """The services and actions of every drive of `node` (`add_drive` for each drive)."""

    def __init__(self, node: ServiceHost):
        self.node = node

    def add_drive(self, h: DriveHandle, ns: str) -> None:
        """The services and actions of drive h, under the namespace ns (`~/<drive>/`)."""
        node = self.node
        srv = [(SetBool, 'enable', self.srv_enable), (Trigger, 'stop', self.srv_stop),
               (Trigger, 'home', self.srv_home), (Trigger, 'fault_reset', self.srv_fault_reset),
               (Trigger, 'save_params', self.srv_save_params),
               (ReadRegister, 'read_register', self.srv_read_register),
               (WriteRegister, 'write_register', self.srv_write_register)]
        for srv_type, name, fn in srv:
            async def callback(req, resp, h=h, fn=fn):
                with node.handling():
                    return await fn(h, req, resp)
            node.create_service(srv_type, ns + name, callback, callback_group=node.srv_group)

        async def move_to(goal, h=h):
            with node.handling():
                return await self.act_move_to(h, goal)

        async def homing(goal, h=h):
            with node.handling():
                return await self.act_home(h, goal)
        ActionServer(node, MoveTo, ns + 'move_to', execute_callback=move_to,
                     goal_callback=lambda _req: GoalResponse.ACCEPT,
                     cancel_callback=lambda _goal: CancelResponse.ACCEPT,
                     callback_group=node.srv_group)
        ActionServer(node, Home, ns + 'homing', execute_callback=homing,
                     goal_callback=lambda _req: GoalResponse.ACCEPT,
                     cancel_callback=lambda _goal: CancelResponse.ACCEPT,
                     callback_group=node.srv_group)

    # ------------------------------------------------------------------------ awaiting a drive
    async def _next_poll(self, h: DriveHandle, after: int, timeout_s: float = 2.0) -> bool:
        """Await the next snapshot of h that followed write number `after` (False: none within
        timeout_s, or the link is lost). Raises Cancelled once the node shuts down: a service
        or action waiting for its drive then answers, rather than loop on polls that will not
        come."""
        fut: concurrent.futures.Future = concurrent.futures.Future()
        h.bus_owner.wait_poll(h.name, timeout_s, fut.set_result, after_write=after)
        fresh = await self.node.await_future(fut)
        if not fresh and h.bus_owner.stopping:
            raise Cancelled('the node is shutting down')
        return fresh

    async def _run_job(self, h: DriveHandle, command: Command) -> Any:
        return (await self._command(h, command))[0]

    async def _command(self, h: DriveHandle, command: Command) -> tuple[Any, int]:
        """Run `command` on h's drive: (its result, the drive's write count at its end: what
        a snapshot must follow to tell what the command did)."""
        fut = h.bus_owner.submit(h.name, command, hand_over=command.kind == JobKind.URGENT)
        result = await self.node.await_future(fut, bus_owner=h.bus_owner, timeout_s=JOB_TIMEOUT_S)
        return result, fut.after_write

    @staticmethod
    def _since(h: DriveHandle, after: int) -> DriveState | None:
        """h's snapshot when it followed write number `after`, else None (what the drive
        did since is not known yet)."""
        state = h.state
        return state if state.after_write >= after else None

    def _state_text(self, h: DriveHandle, after: int) -> str:
        state = self._since(h, after)
        return state.state.value if state is not None else \
            'state not known yet (no snapshot of the drive since the command)'

    async def _respond(self, h: DriveHandle, resp, work, ok_message: Callable[[Any], str]):
        """Await work(); fill a success/message response; errors become success=false."""
        try:
            result = await work()
            resp.success, resp.message = True, ok_message(result)
        except (CommandRefused, RefusedError, DriveError) as e:
            resp.success, resp.message = False, f'{h.name}: {e}'
            if not isinstance(e, CommandRefused):
                self.node.log.warning(resp.message)
        return resp

    # ------------------------------------------------------------------------------- services
    async def srv_enable(self, h: DriveHandle, req, resp):
        async def work():
            self.node.check_link(h, 'enable' if req.data else 'disable', safe=not req.data)
            if req.data:
                _, after = await self._command(h, Command.enable(h.drive.enable))
            else:
                _, after = await self._command(h, Command.disable(h.drive.disable))
            await self.node.published(h, after=after)
            return self._state_text(h, after)
        return await self._respond(h, resp, work, lambda st: f'{h.name}: {st}')

    async def srv_stop(self, h: DriveHandle, req, resp):
        async def work():
            self.node.check_link(h, 'stop', safe=True)
            _, after = await self._command(h, Command.stop(h.drive.stop))
            await self.node.published(h, after=after)
        return await self._respond(h, resp, work,
                                   lambda _: f'{h.name}: stopping with the profile deceleration')

    async def run_homing(self, h: DriveHandle, feedback: Callable[[], None] | None = None,
                         cancelled: Callable[[], bool] = lambda: False) -> str:
        self.node.check_link(h, 'home')
        if h.state.fault:
            self.node.refuse(h, f'home: drive is in FAULT 0x{h.state.fault_code:04X} '
                           f'({h.state.fault_text}); call fault_reset first')
        homing = h.homing()
        note, after = await self._command(
            h, Command.homing(lambda: h.drive.start_homing(homing)))
        timeout_s = h.param('homing.timeout_s')
        deadline = self.node.get_clock().now().nanoseconds * 1e-9 + timeout_s
        fresh = await self._next_poll(h, after)
        idle_polls = 0         # snapshots in a row that say no homing runs (after its start)
        while True:
            # Only a snapshot read after the homing's start says how it goes: an older one (a
            # poll under way while it started, or the last one when none came since) may show
            # the previous homing's ATTAINED.
            s = self._since(h, after)
            st = s.homing if s is not None else None
            if st == HomingState.ATTAINED:
                await self.node.published(h, after=after)
                s = h.state        # (as new as the one judged, or newer)
                return (f'{h.name}: homed at {h.conv.from_steps(s.position_steps):.6g} '
                        f'({s.position_steps} steps)' + (f'; {note}' if note else ''))
            if s is not None and (st == HomingState.ERROR or s.fault):
                raise DriveError(f'homing failed (state {s.state.value}'
                                 + (f', fault 0x{s.fault_code:04X} {s.fault_text}'
                                    if s.fault else '')
                                 + (f', alarms: {"; ".join(s.alarms)}'
                                    if s.alarms else '') + ')')
            if not h.connected:
                raise DriveError('homing interrupted: link lost')
            if cancelled():
                await self._stop_quietly(h, 'homing cancelled')
                raise DriveError('homing cancelled; drive stopped')
            # The homing ended without a result: a stop (CiA 402 Halt: "interrupted"), a
            # disable or another mode. Each vendor's start_homing returns once it runs, so
            # IDLE now is no late start; SETTLED_POLLS fresh snapshots decide, as for move_to.
            if st != HomingState.IDLE:
                idle_polls = 0
            elif fresh:
                idle_polls += 1
            if idle_polls >= SETTLED_POLLS:       # (s: the snapshot that counted last)
                raise DriveError(f'homing interrupted before it ended (state '
                                 f'{s.state.value}, mode {s.mode}): a stop, a '
                                 'disable or a mode change; not homed')
            if self.node.get_clock().now().nanoseconds * 1e-9 > deadline:
                await self._stop_quietly(h, 'homing timeout')
                raise DriveError(f'homing timed out after {timeout_s:g} s (homing.timeout_s); '
                                 'drive stopped')
            if feedback:
                feedback()
            fresh = await self._next_poll(h, after, 1.0)

    async def _stop_quietly(self, h: DriveHandle, why: str) -> None:
        try:
            await self._run_job(h, Command.stop(h.drive.stop, f'stop ({why})'))
        except DriveError as e:
            self.node.log.error(f'{h.name}: stop ({why}) failed: {e}')

    async def srv_home(self, h: DriveHandle, req, resp):
        return await self._respond(h, resp, lambda: self.run_homing(h), lambda msg: msg)

    async def srv_fault_reset(self, h: DriveHandle, req, resp):
        async def work():
            if h.slot.identity_recheck:
                # not driven for its identity: checked again now (a connect, nothing moves)
                try:
                    await self.node.await_future(h.bus_owner.recheck(h.name))
                except Cancelled:
                    raise
                except DriveError as e:
                    if h.slot.not_driven:
                        raise DriveError(f'still not driven: {h.slot.not_driven}') from None
                    raise DriveError(f'checked again: {e}; DISCONNECTED, reconnecting') from None
                await self.node.published(h)
                return f'the identity matches again: driven, state {h.state.state.value}'
            self.node.check_link(h, 'fault_reset')
            remaining, after = await self._command(h, Command.fault_reset(h.drive.fault_reset))
            await self.node.published(h, after=after)
            if remaining:
                raise DriveError(f'fault remains: {remaining}')
            return f'fault cleared, state {self._state_text(h, after)}'
        return await self._respond(h, resp, work, lambda text: f'{h.name}: {text}')

    async def srv_save_params(self, h: DriveHandle, req, resp):
        async def work():
            self.node.check_link(h, 'save_params')
            return await self._run_job(h, Command.maintenance(h.drive.save_params,
                                                              'save_params'))
        return await self._respond(h, resp, work, lambda note: f'{h.name}: parameters saved'
                                   + (f'; {note}' if note else ''))

    async def srv_read_register(self, h: DriveHandle, req, resp):
        resp.value, resp.text = 0, ''

        async def work():
            self.node.check_link(h, 'read_register', safe=True)
            value = await self._run_job(h, Command.maintenance(
                lambda: h.drive.read_register(req.address, req.data_type),
                f'read_register {req.address}'))
            if isinstance(value, str):
                resp.text = value
            else:
                resp.value = int(value)
            return value
        return await self._respond(h, resp, work,
                                   lambda v: f'{req.address} ({req.data_type}) = {v}')

    async def srv_write_register(self, h: DriveHandle, req, resp):
        value = req.text if req.data_type.lower() == 'string' else req.value

        async def work():
            if not h.param('allow_raw_write'):
                self.node.refuse(h, f'write_register {req.address}: raw writes are disabled '
                               f'(set drives.{h.name}.allow_raw_write: true)')
            self.node.check_link(h, 'write_register')
            await self._run_job(h, Command.raw_write(
                lambda: h.drive.write_register(req.address, req.data_type, value),
                f'write_register {req.address}'))
        return await self._respond(h, resp, work,
                                   lambda _: f'{req.address} ({req.data_type}) := {value}')

    # -------------------------------------------------------------------------------- actions
    async def act_move_to(self, h: DriveHandle, goal_handle):
        result = MoveTo.Result()
        target = goal_handle.request.position
        try:
            steps = self.node.check_position(h, 'move_to', target)
            motion = h.motion()
            _, after = await self._command(
                h, Command.move(lambda: h.drive.move_to(steps, motion), f'move_to {target}'))
            fb = MoveTo.Feedback()
            settled, last = 0, None
            await self._next_poll(h, after)
            while True:
                fresh = await self._next_poll(h, after, 1.0)
                if not fresh and not h.connected:
                    raise DriveError('move aborted: link lost')
                s = self._since(h, after)     # None: nothing read since the move was sent
                if s is not None and s.fault:
                    raise DriveError(f'move aborted: state {s.state.value} {s.fault_text}'.strip())
                if goal_handle.is_cancel_requested:
                    await self._stop_quietly(h, 'move_to cancelled')
                    goal_handle.canceled()
                    result.message, result.final_position = 'cancelled; drive stopped', h.position
                    return result
                # decided on SETTLED_POLLS snapshots in a row that agree: standstill at one
                # position (one snapshot may mix an old position with a new status), each read
                # after the move was sent
                if fresh and s is not None:     # a snapshot counts once
                    still = not s.moving and (s.target_reached or abs(
                        s.position_steps - steps) <= TARGET_TOLERANCE_STEPS)
                    settled = settled + 1 if still and last == s.position_steps else int(still)
                    last = s.position_steps
                if settled >= SETTLED_POLLS:
                    if abs(s.position_steps - steps) <= TARGET_TOLERANCE_STEPS:
                        break
                    raise DriveError(f'drive stopped at {h.position:.6g}, not at {target:.6g}')
                fb.position, fb.state = h.position, h.state.state.value
                fb.distance_remaining = target - h.position
                goal_handle.publish_feedback(fb)
            await self.node.published(h, after=after)
            goal_handle.succeed()
            result.success, result.message = True, f'{h.name}: at {h.position:.6g}'
        except (CommandRefused, DriveError) as e:
            goal_handle.abort()
            result.success, result.message = False, f'{h.name}: {e}'
        result.final_position = h.position
        return result

    async def act_home(self, h: DriveHandle, goal_handle):
        result = Home.Result()
        fb = Home.Feedback()

        def feedback():
            fb.homing_state, fb.position = h.state.homing.value, h.position
            goal_handle.publish_feedback(fb)
        try:
            result.message = await self.run_homing(
                h, feedback, lambda: goal_handle.is_cancel_requested)
            result.success = True
            goal_handle.succeed()
        except (CommandRefused, DriveError) as e:
            result.success, result.message = False, f'{h.name}: {e}'
            if goal_handle.is_cancel_requested:
                goal_handle.canceled()
            else:
                goal_handle.abort()
        result.final_position = h.position
        return result

