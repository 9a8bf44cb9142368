"""Derivatives of the contact residual for the adjoint: states, rest shape and friction."""

__all__: list[str] = []
