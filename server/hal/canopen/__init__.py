"""The `canopen` HAL backend: CiA 402 servo drives over CANopen, and simulated drives to test it.

See docs/drives.md. `create_canopen_hal` in `master.py` is the factory the service's
`--backend canopen` uses.
"""
