"""The benchmark side: error metrics (:mod:`.metrics`), scoring against an optical reference
(:mod:`.scoring`), readers of the public recordings (:mod:`.datasets`) and figures
(:mod:`.plots`). Nothing here runs inside a filter."""
