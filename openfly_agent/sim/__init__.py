"""Level-1 simulators: the Simulator protocol, flight dynamics, the embedded city, engine bridges."""
