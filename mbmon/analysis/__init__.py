"""Analysis beside the one flow: finding Modbus on any port (:mod:`.detect`).

Each module is imported only by the command or option that uses it: nothing
here is imported by ``import mbmon``.
"""
