"""What the nodes decide, without middleware: pure functions and dataclasses under ``ros/``.

:mod:`.interface` describes each node's parameters and topics as data; :mod:`.safety_filter`
is the filter node's whole decision (validate, build, filter, fail safe); :mod:`.scene` builds
the scene markers; :mod:`.interface_doc` prints the README's interface tables. Nothing here
imports a runtime, so the offline tools (``rcbf_ros refilter``) and the tests call it directly.
"""
