"""A module only `test_started_workers_import_the_preload_and_run_the_tasks` imports, in Ray workers: its
presence in a worker's `sys.modules` shows that the worker ran the warm-up task."""
