"""The wire contract: pydantic models of every bus message and configuration."""
