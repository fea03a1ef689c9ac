"""The MuJoCo back end: scene model building (world.py), below every stage that needs a model.

It imports the core, the schema and the catalog, never a stage.
"""
