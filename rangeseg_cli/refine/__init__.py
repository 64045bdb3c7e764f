"""The refinement after growing, beyond the paper.

One table of passes (:mod:`rangeseg_cli.refine.passes`) that cut, merge and
assign with one fit test scaled by the image's noise.
"""
