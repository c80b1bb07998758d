"""Running the experiment on the graph: the orchestrator and its client node, seeds in
parallel, processes, ROS domains, network namespaces and what every process needs to end."""
