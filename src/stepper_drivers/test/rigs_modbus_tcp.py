"""A Modbus TCP peer played by hand (protocol/test_modbus_tcp_bus.py, vendors/
test_malformed_answers.py)."""

import socket
import threading


class ScriptedServer:
    """A Modbus TCP server played by hand on a plain socket: `answer(request_adu)` returns the
    bytes to send back (or None for silence), so late and foreign replies can be staged."""

    def __init__(self, answer):
        self.listener = socket.create_server(('127.0.0.1', 0))
        self.port = self.listener.getsockname()[1]
        self.answer = answer
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self):
        peer, _ = self.listener.accept()
        with peer:
            while True:
                adu = peer.recv(260)
                if not adu:
                    return
                reply = self.answer(adu)
                if reply:
                    peer.sendall(reply)

    def close(self):
        self.listener.close()
