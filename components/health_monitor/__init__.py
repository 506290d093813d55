"""Health monitor: one module's components, topics, motors and computer as one DiagnosticArray."""
