"""The component launcher: which processes run on this computer, and a supervisor for them."""
