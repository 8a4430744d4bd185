"""The asyncio orchestration: control loop, rider commands, safety, service integration."""
