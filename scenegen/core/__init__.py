"""The pure scene core: the geometry and facts every stage shares, as numbers (numpy, the schema, the
asset catalog; no MuJoCo, no renderer): ``layout`` (table, furniture, support surfaces),
``rotations``."""
