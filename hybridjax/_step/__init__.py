"""One solver step: an explicit Runge-Kutta step and the step-size rule, written out for XLA."""
