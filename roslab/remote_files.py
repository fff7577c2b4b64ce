"""How every file roslab writes reaches a host: never through a link, never half-written.

pyinfra 3.10 uploads a file for a sudo operation by SFTP into `/tmp/pyinfra-<sha1 of the
destination>` (as the login user, mode 0644 whatever it holds), then runs
`sudo cp TEMP DEST` and `rm TEMP`. `cp` follows a symbolic link at DEST: a unit masked with
`systemctl mask` (a link to /dev/null) was "written" into /dev/null, and files.put's
chmod/chown after it turned /dev/null into a 0644 regular file, which broke SFTP (and
so the next run) for that host. A link made by someone else in ~/ or /etc would have
let them choose which file root writes. And an SFTP failure is not an error pyinfra
keeps to one host: it stopped the run for every host.

`install()` replaces the SSH connector's `put_file` (used by files.put, files.template
and roslab's own FileUploadCommands) with `put_file` below: the content travels base64 on
the stdin of ONE command (with the operation's sudo, if any; no SFTP, nothing on the disk
as the login user, no predictable temp name), which runs `WRITE_SCRIPT` with the host's
python3. That script

- refuses a destination that is a symbolic link, or not a regular file, or has other
  hard links, saying so in one line starting with "roslab:" (the run summary's reason);
- refuses a directory on the way that is a symbolic link made by a user other than root
  or the user writing (a student's `~/ros2_ws -> /etc`);
- writes a new file in the destination's directory (O_EXCL, mode 0600 from its first
  byte), gives it the old file's owner and mode (or the mode the upload asks for; a new
  file gets 0644 less the umask, as `cp` gives), and renames it over the destination:
  a rename replaces a name, it never follows a link, and nobody ever sees half a file.

`OwnedFileUpload` is a FileUploadCommand that also gives the file its owner and mode
before it takes the destination's name (roslab.ops.files' managed files: ~/.bashrc, ...),
so no chown or chmod follows the upload (they would follow a link put there in between).
"""

from __future__ import annotations

import base64
from io import BytesIO, StringIO

from pyinfra import logger
from pyinfra.api import QuoteString, StringCommand
from pyinfra.api.command import FileUploadCommand
from pyinfra.api.exceptions import ConnectError
from pyinfra.api.util import get_file_io

# Exit status of WRITE_SCRIPT when it refuses the destination (its message is on stderr).
REFUSED = 3

# Runs on the host with its python3 (3.6+), as root for a sudo operation.
# argv: DEST [MODE|-] [USER:GROUP] (either side may be empty).
WRITE_SCRIPT = r'''
import base64, os, stat, sys, tempfile
def refuse(message):
    sys.stderr.write("roslab: " + message + "\n")
    sys.exit(3)
data = base64.b64decode(sys.stdin.buffer.read())
dest = sys.argv[1]
mode = int(sys.argv[2], 8) if len(sys.argv) > 2 and sys.argv[2] != "-" else None
owner = sys.argv[3].split(":", 1) if len(sys.argv) > 3 else ["", ""]
uid = gid = -1
try:
    if owner[0]:
        import pwd
        uid = pwd.getpwnam(owner[0]).pw_uid
    if len(owner) > 1 and owner[1]:
        import grp
        gid = grp.getgrnam(owner[1]).gr_gid
except KeyError as missing:
    refuse("cannot give %s to %s: no such user or group" % (dest, missing))
if not dest.startswith("/") or "/../" in dest + "/" or dest.endswith("/"):
    refuse("%s is not an absolute file path" % dest)
directory, name = os.path.split(dest)
writer = os.geteuid()
path = ""
for part in directory.split("/"):
    if not part:
        continue
    path += "/" + part
    try:
        info = os.lstat(path)
    except FileNotFoundError:
        refuse("cannot write %s: the directory %s does not exist" % (dest, path))
    if stat.S_ISLNK(info.st_mode) and info.st_uid not in (0, writer):
        refuse("will not write %s: %s is a symbolic link (to %s) made by uid %d, not by roslab"
               % (dest, path, os.readlink(path), info.st_uid))
try:
    old = os.lstat(dest)
except FileNotFoundError:
    old = None
if old is not None:
    if stat.S_ISLNK(old.st_mode):
        refuse("will not write %s: it is a symbolic link (to %s) that roslab did not make"
               % (dest, os.readlink(dest)))
    if not stat.S_ISREG(old.st_mode):
        refuse("will not write %s: it is not a regular file" % dest)
    if old.st_nlink > 1:
        refuse("will not write %s: it has %d hard links, roslab did not make them" % (dest, old.st_nlink))
umask = os.umask(0o077)
fd, temporary = tempfile.mkstemp(dir=directory, prefix="." + name[:40] + ".roslab-")
try:
    with os.fdopen(fd, "wb") as out:
        out.write(data)
        out.flush()
        os.fsync(out.fileno())
        if writer == 0 and (old is not None or uid != -1 or gid != -1):
            os.fchown(out.fileno(), uid if uid != -1 else (old.st_uid if old else -1),
                      gid if gid != -1 else (old.st_gid if old else -1))
        if mode is None:
            mode = stat.S_IMODE(old.st_mode) if old is not None else 0o666 & ~umask
        os.fchmod(out.fileno(), mode)
    os.rename(temporary, dest)
except BaseException:
    try:
        os.unlink(temporary)
    except OSError:
        pass
    raise
# The rename itself reaches the disk (a power cut right after keeps the new file, on a Pi's FAT
# boot partition too); a filesystem that cannot sync a directory has nothing more to give.
try:
    folder = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(folder)
    finally:
        os.close(folder)
except OSError:
    pass
'''


def write_command(dest: str, mode: int | None = None, user: str | None = None,
                  group: str | None = None) -> StringCommand:
    """The command that writes its stdin (base64) to `dest` (see WRITE_SCRIPT)."""
    bits = ["python3", "-c", QuoteString(WRITE_SCRIPT), QuoteString(dest)]
    if mode is not None or user or group:
        bits.append(f"{mode:o}" if mode is not None else "-")
    if user or group:
        bits.append(QuoteString(f"{user or ''}:{group or ''}"))
    return StringCommand(*bits)


def encoded(filename_or_io) -> str:
    """The content of a local file or IO object, base64, one line."""
    if isinstance(filename_or_io, StringIO):
        filename_or_io = BytesIO(filename_or_io.getvalue().encode())
    with get_file_io(filename_or_io, "rb") as file_io:
        data = file_io.read()
    if isinstance(data, str):
        data = data.encode()
    return base64.b64encode(data).decode("ascii")


def put_file(self, filename_or_io, remote_filename, remote_temp_filename=None,
             print_output: bool = False, print_input: bool = False, mode: int | None = None,
             user: str | None = None, group: str | None = None, **arguments) -> bool:
    """The SSH connector's `put_file`, through `write_command` (`remote_temp_filename` unused:
    nothing is put in a temporary file as the login user)."""
    arguments.pop("_chdir", None)
    arguments.pop("_stdin", None)  # the content is this command's stdin
    content = encoded(filename_or_io)
    try:
        ok, output = self.run_shell_command(
            write_command(str(remote_filename), mode, user, group),
            print_output=print_output, print_input=print_input, _stdin=content, **arguments,
        )
    except ConnectError as exc:  # a PyinfraError would stop every host; this is one host's
        raise OSError(f"roslab: could not write {remote_filename}: {exc}") from exc
    if not ok:
        lines = [line for line in output.stderr_lines if line.strip()]
        own = [line for line in lines if line.startswith("roslab:")]
        reason = (own or lines or ["the write failed without a message"])[-1]
        if not reason.startswith("roslab:"):
            reason = f"roslab: could not write {remote_filename}: {reason}"
        self.host.log_styled(reason, fg="red", log_func=logger.error)
        return False
    if print_output:
        self.host.log(f"file uploaded: {remote_filename}")
    return True


class OwnedFileUpload(FileUploadCommand):
    """An upload that has its owner and mode before it takes the destination's name, so no
    chown/chmod has to follow it (they would follow a link put there in between)."""

    def __init__(self, src, dest, user: str | None = None, group: str | None = None,
                 mode: int | str | None = None, **kwargs):
        super().__init__(src, dest, **kwargs)
        self.user, self.group = user, group
        self.mode = int(str(mode), 8) if mode is not None else None

    def execute(self, state, host, connector_arguments):
        connector_arguments.update(self.connector_arguments)
        return host.put_file(
            self.src, self.dest, print_output=state.print_output, print_input=state.print_input,
            mode=self.mode, user=self.user, group=self.group, **connector_arguments,
        )


def install() -> None:
    """Make pyinfra's SSH connector upload with `put_file` above. Idempotent."""
    from pyinfra.connectors.ssh import SSHConnector

    SSHConnector.put_file = put_file  # type: ignore[method-assign]  # roslab patches pyinfra here on purpose
