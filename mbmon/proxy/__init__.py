"""The active proxy: an asyncio Modbus/TCP engine (:mod:`.engine`) and its
write guard (:mod:`.guard`, pure). ``mbmon proxy`` wires them to the hub."""
