"""The motor interface component: one module's motors on the data plane."""
