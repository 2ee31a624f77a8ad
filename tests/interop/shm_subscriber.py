"""Receives one warped volume through iceoryx2's Python binding (the header as a ctypes
struct, the samples as a slice of c_float: its length is in bytes, not elements). Prints
one JSON object with the header and a checksum of the samples.

usage: shm_subscriber.py SERVICE_NAME
"""

import ctypes
import json
import sys
import time

import iceoryx2 as iox2


class WarpedVolumeHeader(ctypes.Structure):
    _fields_ = [
        ("sequence", ctypes.c_uint64),
        ("stamp_sec", ctypes.c_int32),
        ("stamp_nanosec", ctypes.c_uint32),
        ("dims", ctypes.c_uint32 * 3),
        ("padding", ctypes.c_uint32),
        ("spacing", ctypes.c_double * 3),
        ("origin", ctypes.c_double * 3),
    ]

    @staticmethod
    def type_name() -> str:
        return "WarpedVolumeHeader"


def main():
    iox2.set_log_level_from_env_or(iox2.LogLevel.Warn)
    node = iox2.NodeBuilder.new().create(iox2.ServiceType.Ipc)
    service = (
        node.service_builder(iox2.ServiceName.new(sys.argv[1]))
        .publish_subscribe(iox2.Slice[ctypes.c_float])
        .user_header(WarpedVolumeHeader)
        .open()
    )
    subscriber = service.subscriber_builder().create()
    deadline = time.time() + 10
    while time.time() < deadline:
        sample = subscriber.receive()
        if sample is not None:
            header = sample.user_header().contents
            payload = sample.payload()
            count = payload.number_of_elements
            values = ctypes.cast(payload.data_ptr, ctypes.POINTER(ctypes.c_float))
            n = header.dims[0] * header.dims[1] * header.dims[2]
            elements = count if count == n else count // 4
            total = sum(values[i] for i in range(elements))
            print(json.dumps({"sequence": header.sequence, "dims": list(header.dims), "spacing": list(header.spacing), "origin": list(header.origin), "elements": elements, "sum": total, "first": values[0], "last": values[elements - 1]}))
            return
        time.sleep(0.01)
    print(json.dumps({"error": "no sample within 10 s"}))
    sys.exit(1)


if __name__ == "__main__":
    main()
