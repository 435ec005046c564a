"""The managed (lifecycle) variant of every vendor node: executables `<key>_lifecycle_node`.

The node is named like the plain one (`<key>_node`), so the same params file applies. Its
transitions, as a lifecycle manager (nav2's, or launch's lifecycle events) drives them through
the standard services (~/change_state, ~/get_state, ~/get_available_transitions):
- on_configure: builds the buses and their owner threads, opens each bus and reads every drive's
  identity and state; FAILURE (back to unconfigured, everything closed again) when a drive does
  not answer within CONFIGURE_TIMEOUT_S or is not the drive configured, with the one-line errors
  of the plain node. Polling starts here: an X-PLUS MT's watchdog (1097) and an RD4's are fed from
  now on, and a Vector Step gets its SYNC.
- on_activate: joint_states, status and diagnostics go out, commands are taken, and drives with
  auto_enable are enabled (never another one).
- on_deactivate: every drive is stopped (the running trajectory too), commands are refused;
  polling goes on (the drives' watchdogs stay fed). A stop, a disable and raw reads are taken
  in every state.
- on_cleanup: the drives are stopped, disabled where disable_on_shutdown, the buses closed.
- on_shutdown and on_error: the drives are stopped and disabled, every one, the buses closed.
"""

from __future__ import annotations

import time

from rclpy.lifecycle import LifecycleNodeMixin, LifecycleState, TransitionCallbackReturn

from ..owner.commands import Command
from .node import SHUTDOWN_STOP_TIMEOUT_S, DriveNode

# How long on_configure waits for every drive's first connect (identity and state read).
CONFIGURE_TIMEOUT_S = 10.0
# How long on_deactivate waits for the drives' stops to be confirmed.
DEACTIVATE_STOP_TIMEOUT_S = 2.0
POLL_S = 0.02


class ManagedDriveNode(LifecycleNodeMixin, DriveNode):

    def __init__(self, vendor, node_name, config_loader):
        DriveNode.__init__(self, vendor, node_name, config_loader, managed=True)
        LifecycleNodeMixin.__init__(self, enable_communication_interface=True)
        self._configured = False
        self._label = 'unconfigured'

    def lifecycle_state_label(self) -> str:
        return self._label

    # ----------------------------------------------------------------------------- transitions
    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.build()
        self.start()
        deadline = time.monotonic() + CONFIGURE_TIMEOUT_S
        while True:
            slots = [h.slot for h in self.handles.values()]
            # (the identity error alone: a failed configure closes the bus, nothing is checked
            # again)
            problems = [f'{s.name}: not driven: '
                        + (s.last_error if s.identity_recheck else s.not_driven)
                        for s in slots if s.not_driven]
            if problems:
                break
            if all(s.connected and s.polls for s in slots):
                break
            if time.monotonic() >= deadline:
                problems = [f'{s.name}: no answer within {CONFIGURE_TIMEOUT_S:g} s'
                            + (f' ({s.last_error})' if s.last_error else '')
                            for s in slots if not s.connected]
                break
            time.sleep(POLL_S)
        if problems:
            for p in problems:
                self.log.error(f'configure failed: {p}')
            self._close(disable_all=False)
            return TransitionCallbackReturn.FAILURE
        self._configured = True
        self._label = 'inactive'
        self.log.info('configured: ' + ', '.join(
            f'{h.name} {h.state.state.value}' for h in self.handles.values()))
        return super().on_configure(state)

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        result = super().on_activate(state)       # the lifecycle publishers
        self.accepting = True
        self._label = 'active'
        for h in self.handles.values():
            if h.cfg.params.get('auto_enable'):
                h.bus_owner.submit(h.name, Command.enable(h.drive.enable, 'auto_enable')) \
                    .add_done_callback(lambda f, h=h: self._auto_enabled(h, f))
        self.log.info('active: commands are taken')
        return result

    def _auto_enabled(self, h, fut) -> None:
        exc = fut.exception()
        if exc is None:
            self.log.info(f'{h.name}: enabled at activation (auto_enable)')
        else:
            self.log.error(f'{h.name}: auto_enable failed: {exc}')

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.accepting = False
        self._label = 'inactive'
        self._stop_all('deactivate')
        self.log.info('inactive: every drive stopped, commands refused')
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._close(disable_all=False)
        self.log.info('unconfigured: buses closed')
        return super().on_cleanup(state)

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.accepting = False
        self._close(disable_all=True)
        self._label = 'finalized'
        return super().on_shutdown(state)

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.accepting = False
        self._close(disable_all=True)
        return super().on_error(state)

    # -------------------------------------------------------------------------------- helpers
    def _stop_all(self, why: str) -> None:
        self.trajectories.follower.stop(f'node {why}')
        futs = [h.bus_owner.submit(h.name, Command.stop(h.drive.stop, f'{why}: stop'))
                for h in self.handles.values() if h.connected]
        deadline = time.monotonic() + DEACTIVATE_STOP_TIMEOUT_S
        for fut in futs:
            try:
                fut.result(max(0.0, deadline - time.monotonic()))
            except Exception as exc:  # noqa: BLE001 - reported, the others still wait
                self.log.error(f'{why}: stop failed: {exc}')

    def _close(self, disable_all: bool) -> None:
        """Stop, wait for standstill (bounded), disable (all, or where disable_on_shutdown),
        close every bus; the bus_owners end."""
        if not self.bus_owners:
            return
        if self._interfaces:
            self.trajectories.follower.stop('node closing')
        self.accepting = False
        for bus_owner in self.bus_owners:
            disable = [n for n in bus_owner.slots
                       if disable_all or self.handles[n].param('disable_on_shutdown')]
            bus_owner.shutdown(SHUTDOWN_STOP_TIMEOUT_S, disable)
        self._configured = False
        self._label = 'unconfigured'

    def shutdown_drives(self) -> None:
        """Process exit (SIGINT, SIGTERM) in any state: as on_shutdown."""
        if self._configured or any(s.alive for s in self.bus_owners):
            self._close(disable_all=True)
