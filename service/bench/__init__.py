"""The bench the service owns: today a simulated one built from a scenario."""
