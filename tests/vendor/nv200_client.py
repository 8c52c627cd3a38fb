"""Run by tests/test_vendor_clients.py under Python >= 3.12 with the vendor's ``nv200``
library: connect to PORT, drive the unit as the library's own examples do, print JSON."""
import asyncio
import json
import sys
import time


async def main(port: str, volts: float) -> dict:
    from nv200.data_recorder import DataRecorder, DataRecorderSource
    from nv200.nv200_device import NV200Device
    from nv200.serial_protocol import SerialProtocol

    t0 = time.monotonic()
    dev = NV200Device(SerialProtocol(port=port))
    await dev.connect(auto_adjust_comm_params=False)
    out = {"connect_s": time.monotonic() - t0}
    out["voltage_range_V"] = list(await dev.get_voltage_range())
    out["position_range"] = list(await dev.get_position_range())
    out["voltage_unit"] = await dev.get_voltage_unit()
    out["position_unit"] = await dev.get_position_unit()
    out["temperature_C"] = await dev.get_heat_sink_temperature()
    out["actuator"] = await dev.get_actuator_name()
    status = await dev.get_status_register()
    out["status_word"] = status.value
    await dev.move_to_voltage(volts)
    out["setpoint"] = await dev.get_setpoint()
    out["meas"] = await dev.get_current_position()
    out["piezo_voltage_V"] = await DataRecorder(dev).read_single_value_from(DataRecorderSource.PIEZO_VOLTAGE)
    await dev.close()
    return out


if __name__ == "__main__":
    print(json.dumps(asyncio.run(main(sys.argv[1], float(sys.argv[2])))))
