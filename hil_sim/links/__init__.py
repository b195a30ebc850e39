"""Link emulators: pty UART, TCP, XBee module, CAN node (virtual bus and slcan), fault injection."""
