# Convenience wrappers; the README's two commands are scripts/demo and scripts/test.
.PHONY: setup demo test check
setup: ; @scripts/setup
demo: ; @scripts/demo
test: ; @scripts/test
check: ; @scripts/check
