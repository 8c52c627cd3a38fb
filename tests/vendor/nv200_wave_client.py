"""Run by tests/test_vendor_clients.py under Python >= 3.12 with the vendor's ``nv200``
library: upload a 12-point sine as the arbitrary waveform (in volts, 0.2 ms per sample), run
it CYCLES times with the library's WaveformGenerator, wait for the end, print JSON.

Short on purpose: the library waits 0.4 s for a possible error reply after every write (a
write that succeeds gets none), so each ``gbarb`` buffer slot costs 0.4 s."""
import asyncio
import json
import math
import sys


async def main(port: str, cycles: int) -> dict:
    from nv200.nv200_device import NV200Device
    from nv200.serial_protocol import SerialProtocol
    from nv200.waveform_generator import WaveformGenerator, WaveformUnit

    dev = NV200Device(SerialProtocol(port=port))
    await dev.connect(auto_adjust_comm_params=False)
    gen = WaveformGenerator(dev)
    wave = WaveformGenerator.WaveformData(
        values=[30.0 + 20.0 * math.sin(2 * math.pi * k / 12) for k in range(12)], sample_time_ms=0.2)
    await gen.set_waveform(wave, unit=WaveformUnit.VOLTAGE)
    out = {"points": len(wave.values), "sample_time_ms": wave.sample_time_ms,
           "values_V": [float(v) for v in wave.values], "loop": await gen.get_loop_settings(),
           "readback_pct": await gen.read_waveform_buffer(0, 4)}
    await gen.start(cycles=cycles)   # 3 x 12 x 0.2 ms: over before the library's write returns
    out["finished"] = await gen.wait_until_finished(timeout_s=10.0)
    out["running_at_end"] = await gen.is_running()
    await gen.start(cycles=WaveformGenerator.NV200_INFINITE_CYCLES)
    out["endless_running"] = await gen.is_running()
    await gen.stop()
    out["running_after_stop"] = await gen.is_running()
    await dev.close()
    return out


if __name__ == "__main__":
    print(json.dumps(asyncio.run(main(sys.argv[1], int(sys.argv[2])))))
