"""The Zenoh plumbing every uavmm process shares: options, sessions, publishers, guarded callbacks.

`shared/` stays free of I/O (DESIGN.md section 1); this package is the one place that knows how uavmm
opens Zenoh sessions (`transport.session`), declares publishers (`transport.publishers`), turns the
command-line options into a ``zenoh.Config`` (`transport.options`) and keeps a bad message or a bug in a
callback from reaching Zenoh's threads (`transport.guard`). The agent and the fusion server build on it;
it imports nothing above `shared/`.
"""
