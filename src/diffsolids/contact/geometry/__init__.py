"""Contact geometry: the collision surface of the bodies, obstacles and their flat regions."""

__all__: list[str] = []
