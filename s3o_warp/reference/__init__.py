"""Dense pure-torch twins of every Warp op (``<op>_reference``, same signature): the right answers.

They are short and O(everything) on purpose: tests compare the Warp ops against them (values and
gradients, float64) and the benchmarks time them side by side.
"""
