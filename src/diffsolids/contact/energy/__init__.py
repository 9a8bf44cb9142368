"""The contact energy: barrier and friction potentials, their evaluation, lagging and pattern."""

__all__: list[str] = []
