"""What the measuring scripts share about a wall of local nodes."""
import socket


def free_ports(n):
    """`n` loopback UDP ports free now (bound, read, released: a node binds them next)."""
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(n)]
    for s in socks:
        s.bind(("127.0.0.1", 0))
    ports = [s.getsockname()[1] for s in socks]
    for s in socks:
        s.close()
    return ports
