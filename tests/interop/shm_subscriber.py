"""Receives one warped volume through iceoryx2's Python binding (the header as a ctypes
struct, the samples as a slice of c_float: its length is in bytes, not elements). Prints
one JSON object with the header and a checksum of the samples.

With --check-against FILE it also places voxels by the header (origin + direction ·
(index · spacing)) and compares them with where SimpleITK puts the same voxels of FILE, and
their values with FILE's: the largest point and value differences go into the JSON.

With --hoard it never lets a sample go: it borrows every sample it can, prints
{"holding": N} once it can borrow no more, and keeps them until it is killed (a subscriber
that misbehaves; the publisher must not block on it).

usage: shm_subscriber.py SERVICE_NAME [--check-against FILE | --hoard]
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
        ("direction", ctypes.c_double * 9),
    ]

    @staticmethod
    def type_name() -> str:
        return "WarpedVolumeHeader"


def place(header, index):
    """origin + direction · (index · spacing), the direction row major."""
    scaled = [index[a] * header.spacing[a] for a in range(3)]
    d = header.direction
    return [header.origin[r] + sum(d[3 * r + c] * scaled[c] for c in range(3)) for r in range(3)]


def check(header, values, path):
    import SimpleITK as sitk

    image = sitk.ReadImage(path)
    nx, ny, nz = header.dims[0], header.dims[1], header.dims[2]
    if tuple(image.GetSize()) != (nx, ny, nz):
        return {"error": f"sizes differ: {image.GetSize()} in the file, {(nx, ny, nz)} published"}
    worst_point, worst_value, checked = 0.0, 0.0, 0
    for k in range(nz):
        for j in range(0, ny, 2):
            for i in range(0, nx, 3):
                ours = place(header, (i, j, k))
                itk = image.TransformIndexToPhysicalPoint((i, j, k))
                worst_point = max(worst_point, max(abs(ours[a] - itk[a]) for a in range(3)))
                worst_value = max(worst_value, abs(values[i + nx * (j + ny * k)] - image.GetPixel(i, j, k)))
                checked += 1
    return {"checked": checked, "max_point_error_mm": worst_point, "max_value_error": worst_value}


def hoard(subscriber):
    held = []
    deadline = time.time() + 20
    while time.time() < deadline:
        try:
            sample = subscriber.receive()
        except Exception:  # the subscriber's borrow limit: it holds all it may
            break
        if sample is not None:
            held.append(sample)
        else:
            time.sleep(0.005)
    print(json.dumps({"holding": len(held)}), flush=True)
    while True:
        time.sleep(1)


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
    if "--hoard" in sys.argv:
        hoard(subscriber)
        return
    deadline = time.time() + 20
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
            result = {
                "sequence": header.sequence,
                "dims": list(header.dims),
                "spacing": list(header.spacing),
                "origin": list(header.origin),
                "direction": list(header.direction),
                "elements": elements,
                "sum": total,
                "first": values[0],
                "last": values[elements - 1],
            }
            if "--check-against" in sys.argv:
                result.update(check(header, values, sys.argv[sys.argv.index("--check-against") + 1]))
            print(json.dumps(result))
            return
        time.sleep(0.01)
    print(json.dumps({"error": "no sample within 20 s"}))
    sys.exit(1)


if __name__ == "__main__":
    main()
