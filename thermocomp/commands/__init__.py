"""Handlers of the commands that belong to no lower layer: model, simulate, virtual-cnc, hal-plant."""
