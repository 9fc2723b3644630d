"""Thin Python SDK for the catalign registration service (httpx and numpy only)."""

__all__: list[str] = []
