"""The rclpy plumbing of formation's nodes (every module here imports rclpy).

:mod:`rclpy_internals` (the one adapter to what rclpy keeps private: raw wait sets and takes, the
clock's handle, its error type), :mod:`parameters` (declaring and reading a node's parameters),
:mod:`shutdown` (SIGINT and SIGTERM end a node's loop; nothing is raised) and :mod:`param_cli`
(``formation-param``: read and set the parameters of any running node).
"""
