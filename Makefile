# Convenience wrappers; ./dev works without make (a fresh Debian has no make).
.PHONY: demo test bench lint env
demo: ; ./dev demo
test: ; ./dev test
bench: ; ./dev bench
lint: ; ./dev lint
env: ; ./dev env
