"""What a deploy run tells the teacher: the per-host summary and the record of each host's last run."""
