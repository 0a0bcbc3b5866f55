"""The paper's protocols, auto-labelling of captures, timing and the report."""
