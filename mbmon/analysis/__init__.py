"""Analysis beside the one flow: Modbus found on any port (:mod:`.detect`),
rotating ``-w`` rings (:mod:`.rotate`), trigger windows (:mod:`.trigger`) and
the report's figures (:mod:`.report`).

Each module is imported only by the command or option that uses it: nothing
here is imported by ``import mbmon``.
"""
