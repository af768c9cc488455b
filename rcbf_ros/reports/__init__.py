"""What a run left behind, for people: plots (:mod:`.plots`) and the run summary
(:mod:`.run_summary`, ``rcbf_ros summary``)."""
