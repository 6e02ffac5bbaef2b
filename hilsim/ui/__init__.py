"""hilsim's browser control panel (``hilsim ui``, ``hilsim up … --ui``): :mod:`hilsim.ui.server`."""
