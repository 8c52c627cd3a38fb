"""Run by tests/test_vendor_clients.py under Python >= 3.12 with the vendor's ``nv200``
library: its DataRecorder records the piezo position and voltage on channels 0 and 1,
started by the waveform generator (autostart mode 2), while a 12-point sine plays CYCLES
times; prints JSON with what it read back."""
import asyncio
import json
import math
import sys


async def main(port: str, cycles: int) -> dict:
    from nv200.data_recorder import DataRecorder, DataRecorderSource, RecorderAutoStartMode
    from nv200.nv200_device import NV200Device
    from nv200.serial_protocol import SerialProtocol
    from nv200.waveform_generator import WaveformGenerator, WaveformUnit

    dev = NV200Device(SerialProtocol(port=port))
    await dev.connect(auto_adjust_comm_params=False)
    gen = WaveformGenerator(dev)
    wave = WaveformGenerator.WaveformData(
        values=[60.0 + 40.0 * math.sin(2 * math.pi * k / 12) for k in range(12)], sample_time_ms=5.0)
    await gen.set_waveform(wave, unit=WaveformUnit.VOLTAGE)
    rec = DataRecorder(dev)
    await rec.set_data_source(0, DataRecorderSource.PIEZO_POSITION)
    await rec.set_data_source(1, DataRecorderSource.PIEZO_VOLTAGE)
    await rec.set_autostart_mode(RecorderAutoStartMode.START_ON_WAVEFORM_GEN_RUN)
    await rec.set_recorder_stride(100)               # 100 x 50 us = the waveform's 5 ms
    await rec.set_sample_buffer_size(12 * cycles)
    await rec.start_recording()                      # armed: the generator starts it
    await gen.start(cycles=cycles)
    out = {"finished": await rec.wait_until_finished(timeout_s=10.0)}
    ch0, ch1 = await rec.read_recorded_data()
    out.update(values_V=[float(v) for v in wave.values], position=list(ch0.values), voltage=list(ch1.values),
               sources=[ch0.source.value, ch1.source.value], sample_time_ms=ch0.sample_time_ms)
    await dev.close()
    return out


if __name__ == "__main__":
    print(json.dumps(asyncio.run(main(sys.argv[1], int(sys.argv[2])))))
