"""The plug-in machinery: the block protocol that controllers, observers and policies declare
(:mod:`.blocks`: signals, operators, checks, the generated glue) and the registry that finds them
by name through entry points (:mod:`.registry`)."""
