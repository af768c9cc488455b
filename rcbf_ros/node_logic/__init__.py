"""What the nodes decide, without middleware: the filter's message edge (bytes to checked samples,
answers to bytes) and decision, scene markers, parameter and topic tables."""
