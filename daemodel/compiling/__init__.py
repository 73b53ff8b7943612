"""Compiling a model: structure checks (index per constraint), pruning to the outputs, consistent
initial values, code generation, and the frozen CompiledDAE every method solves."""
