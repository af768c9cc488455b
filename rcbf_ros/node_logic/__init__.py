"""What the nodes decide, as pure functions and dataclasses without middleware: the filter's
checks and decision, scene markers, parameter and topic tables; refilter and tests call it."""
