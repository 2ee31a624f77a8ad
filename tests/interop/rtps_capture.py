"""Counts the RTPS (DDS) datagrams an interface carries, in and out, for a while: a raw
AF_PACKET socket sees every IPv4 frame whatever its port or address. Prints one JSON
object: frames seen, RTPS datagrams among them, and how many came from each source address.

usage: rtps_capture.py INTERFACE SECONDS
"""

import json
import socket
import sys
import time


def main():
    interface, seconds = sys.argv[1], float(sys.argv[2])
    capture = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.ntohs(0x0003))
    capture.bind((interface, 0))
    capture.settimeout(0.2)
    print("ready", file=sys.stderr, flush=True)
    end = time.time() + seconds
    frames = rtps = 0
    sources = {}
    while time.time() < end:
        try:
            frame = capture.recv(65535)
        except socket.timeout:
            continue
        frames += 1
        # Ethernet type IPv4, IP protocol UDP: the UDP payload starts with RTPS's magic.
        if len(frame) > 42 and frame[12:14] == b"\x08\x00" and frame[23] == 17:
            header = (frame[14] & 15) * 4
            if frame[14 + header + 8 : 14 + header + 12] == b"RTPS":
                rtps += 1
                source = socket.inet_ntoa(frame[26:30])
                sources[source] = sources.get(source, 0) + 1
    print(json.dumps({"frames": frames, "rtps": rtps, "sources": sources}))


if __name__ == "__main__":
    main()
