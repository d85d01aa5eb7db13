"""Maps of the core: submaps (immutable local grids that the loop search scores against)."""
