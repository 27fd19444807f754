"""Pipelines: config parsing, DAG, content-addressed cache, runner, executors."""
