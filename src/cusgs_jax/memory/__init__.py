"""Per-model feature memory: PSC banks (:mod:`.psc`) and memory attention (:mod:`.attention`)."""
