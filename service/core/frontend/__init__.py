"""The front ends: per-scan pose tracking.

`scan_matcher.ScanMatcherFrontEnd` (the default, "matcher") predicts, matches each scan against
the active submap in one objective (`matcher`: a correlative search, `search`, over the
likelihood grid, `likelihood`, then Gauss-Newton), with the walls' heading (`walls`, measured by
`heading`) and the motion as priors. `paper.PaperFrontEnd` ("paper") is the IROS 2010 method as
stated, the benchmarks' comparator. `kernels` holds the compiled inner loops.
"""
