"""XBee link: each wire frame is the RF data of one Transmit Request (0x10) in API mode 1 or 2.

The host's XBee sits on a serial port in API mode (AP=1 or AP=2). Outgoing frames go to the
controller's module by its 64-bit address with a rotating, never-zero frame id so that every
request earns a Transmit Status (0x8B); the status feeds the statistics (delivered, MAC retries,
each failure by name). Receive Packets (0x90) from the controller's module carry one wire frame
each and go straight to the receiver. Bad API frames are counted and dropped.
"""

from __future__ import annotations

from typing import Any, ClassVar

from host.transport.base import Transport
from host.transport.serial import ByteStream, check_baud, check_url
from protocol.xbee_frames import (
    MAX_RF_PAYLOAD,
    ApiFrameDecoder,
    FrameType,
    ReceivePacket,
    TransmitRequest,
    TransmitStatus,
    encode_api_frame,
    status_name,
)

DEFAULT_BAUD = 115200  # BD=7: the module must be configured anyway (AP=1/2), so set the rate too
FRAME_ID_MAX = 255
ADDR64_MAX = 0xFFFF_FFFF_FFFF_FFFF
API_MODES = (1, 2)


def check_addr64(addr: object) -> int:
    """A 64-bit address as an int or a hex string such as '0013A20040A1B2C3'."""
    if isinstance(addr, str):
        try:
            addr = int(addr.replace(":", "").replace(" ", ""), 16)
        except ValueError:
            raise ValueError(f"dest_addr64 {addr!r} is not a hex number") from None
    if isinstance(addr, bool) or not isinstance(addr, int) or not 0 <= addr <= ADDR64_MAX:
        raise ValueError(f"dest_addr64 must be a 64-bit address, got {addr!r}")
    return addr


class XBeeTransport(Transport):
    """Wire frames as RF data of XBee API frames over a serial port."""

    scheme: ClassVar[str] = "xbee"
    max_frame_bytes: ClassVar[int | None] = MAX_RF_PAYLOAD

    def __init__(
        self,
        url: str,
        dest_addr64: int | str,
        baudrate: int = DEFAULT_BAUD,
        api_mode: int = 1,
        **serial_options: Any,
    ) -> None:
        super().__init__()
        if api_mode not in API_MODES:
            raise ValueError(f"api_mode must be 1 or 2 (AP setting), got {api_mode!r}")
        self.dest_addr64 = check_addr64(dest_addr64)
        self.api_mode = api_mode
        self._escaped = api_mode == 2
        self._stream = ByteStream(check_url(url), check_baud(baudrate), self, serial_options)
        self._stream.sink = self._on_uart_bytes
        self._decoder = ApiFrameDecoder(escaped=self._escaped)
        self._frame_id = 0

    def describe(self) -> str:
        """E.g. 'xbee /dev/ttyUSB0 @9600 AP=2 → 0013A20040A1B2C3'."""
        return (
            f"xbee {self._stream.url} @{self._stream.baudrate} AP={self.api_mode}"
            f" → {self.dest_addr64:016X}"
        )

    async def _open(self) -> None:
        """Open the serial port with a fresh API decoder."""
        self._decoder = ApiFrameDecoder(escaped=self._escaped)
        await self._stream.open()

    def _write(self, frame: bytes) -> None:
        """Wrap the frame in a Transmit Request and queue it on the UART."""
        request = TransmitRequest(self._next_frame_id(), self.dest_addr64, frame)
        self._stream.write(encode_api_frame(request.frame_data(), self._escaped))
        self.stats.bump("xbee_tx_requests")

    async def _close(self) -> None:
        """Release the serial port."""
        await self._stream.close()

    def _next_frame_id(self) -> int:
        """1..255 rotating; 0 would tell the module not to report a status."""
        self._frame_id = self._frame_id % FRAME_ID_MAX + 1
        return self._frame_id

    def _on_uart_bytes(self, data: bytes) -> None:
        """Decode API frames from the UART and dispatch them by type."""
        for frame_data in self._decoder.feed(data):
            self._dispatch(frame_data)
        for name, value in vars(self._decoder.stats).items():
            self.stats.extra[f"xbee_{name}"] = value

    def _dispatch(self, frame_data: bytes) -> None:
        """One good API frame → receiver or statistics."""
        kind = frame_data[0]
        if kind not in (FrameType.RECEIVE_PACKET, FrameType.TRANSMIT_STATUS):
            self.stats.bump("xbee_unknown_type")
            return
        # Only parsing is guarded: an error above us is not a short frame and must not hide.
        try:
            if kind == FrameType.RECEIVE_PACKET:
                packet = ReceivePacket.parse(frame_data)
            else:
                status = TransmitStatus.parse(frame_data)
        except ValueError:
            self.stats.bump("xbee_short_frames")
            return
        if kind == FrameType.RECEIVE_PACKET:
            self._on_receive(packet)
        else:
            self._on_status(status)

    def _on_receive(self, packet: ReceivePacket) -> None:
        """RF data from the controller's module is one wire frame."""
        if packet.src_addr64 != self.dest_addr64:
            # Another radio on the same PAN: not our controller, never its frames.
            self.stats.bump("xbee_foreign_source")
            return
        self.stats.bump("xbee_rx_packets")
        self._deliver(packet.data)

    def _on_status(self, status: TransmitStatus) -> None:
        """Count delivery, MAC retries and failures by name."""
        self.stats.bump("xbee_retries", status.retries)
        if status.delivery == 0:
            self.stats.bump("xbee_delivered")
        else:
            self.stats.bump("xbee_failed")
            self.stats.bump(f"xbee_{status_name(status.delivery)}")
