"""Pure computation of the powder-line twin: no networking, no global state."""
