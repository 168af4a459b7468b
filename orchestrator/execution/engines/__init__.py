"""The engines, one module each (orchestrator/execution/engine.py says what one implements)."""
