"""Collision detection: collision sets, step bounds (CCD), configuration checks and reach."""

__all__: list[str] = []
