#!/bin/sh
# The container's entry point: started as root, it gives the state directory to the service
# user, then runs the command (default: the daemon) as that user.
#
# Why: BlueOS binds /usr/blueos/extensions/adaptnav onto /var/lib/adaptnav, and Docker creates a
# missing bind source as root:root 0755, where the service user cannot write its learned state
# (each start would begin from the configured motion model again, persistence.failures counting).
# A named volume (podman run -v adaptnav-state:...) already is the user's: chown changes nothing.
set -eu
STATE_DIR=/var/lib/adaptnav
if [ "$(id -u)" = 0 ]; then
    if ! chown -R adaptnav:adaptnav "$STATE_DIR"; then
        echo "adaptnav entrypoint: could not give $STATE_DIR to user adaptnav; learned state may not be saved" >&2
    fi
    exec setpriv --reuid=adaptnav --regid=adaptnav --init-groups -- "$@"
fi
exec "$@"
