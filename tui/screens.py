"""The monitor's other screens: the bias editor and the help."""

from __future__ import annotations

from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Vertical
from textual.screen import ModalScreen
from textual.widgets import DataTable, Input, Label, Markdown

from evcap.acquire import protocol as P
from evcap.errors import InputError


class BiasScreen(ModalScreen):
    """The biases in force; a new value is written to the camera at once."""

    BINDINGS = [Binding("escape", "dismiss", "Back")]
    DEFAULT_CSS = """
    BiasScreen { align: center middle; }
    BiasScreen > Vertical { width: 64; height: 90%; border: thick $primary; background: $surface; }
    BiasScreen DataTable { height: 1fr; }
    BiasScreen #bias-error { color: $error; height: auto; }
    """

    def __init__(self, biases: dict[str, int], apply) -> None:
        super().__init__()
        self.biases = dict(biases)
        self.apply = apply  # called with (name, code): sends the change to the capture thread

    def compose(self) -> ComposeResult:
        with Vertical():
            yield Label("Biases: pick one, type a new value, Enter. Esc goes back.")
            yield DataTable(cursor_type="row", id="bias-table")
            yield Input(placeholder="coarse fine (e.g. 5 255), or a code", id="bias-input")
            yield Label("", id="bias-error")

    def on_mount(self) -> None:
        table = self.query_one(DataTable)
        table.add_columns("bias", "setting", "code")
        for name, code in self.biases.items():
            table.add_row(name, P.describe_bias(name, code), f"0x{code:04X}", key=name)
        table.focus()

    def selected(self) -> str:
        table = self.query_one(DataTable)
        return table.coordinate_to_cell_key(table.cursor_coordinate).row_key.value

    def on_data_table_row_selected(self, event: DataTable.RowSelected) -> None:
        self.query_one(Input).focus()

    def on_input_submitted(self, event: Input.Submitted) -> None:
        name = self.selected()
        try:
            code = P.parse_bias(name, event.value, self.biases[name])
        except InputError as e:
            self.query_one("#bias-error", Label).update(str(e))
            return
        self.query_one("#bias-error", Label).update("")
        self.apply(name, code)
        self.show_bias(name, code)
        event.input.value = ""
        self.query_one(DataTable).focus()

    def show_bias(self, name: str, code: int) -> None:
        self.biases[name] = code
        table = self.query_one(DataTable)
        table.update_cell(name, table.ordered_columns[1].key, P.describe_bias(name, code))
        table.update_cell(name, table.ordered_columns[2].key, f"0x{code:04X}")


HELP = """\
# evcap monitor

| key | |
|---|---|
| `r` | start / stop a recording into a new session file (the monitor only) |
| `b` | the biases: change one, it is written to the camera at once (and logged in the session) |
| `c` | color the event image by polarity (ON green, OFF red) or by Bayer channel |
| `?` | this help |
| `q` | quit (a recording in progress is closed first) |

The event image shows the events of the last 33 ms; the rates are per 100 ms of camera time.
Warnings: the camera lost, the disk almost full, hot pixels making most of the events.
"""


class HelpScreen(ModalScreen):
    BINDINGS = [Binding("escape,question_mark,q", "dismiss", "Back")]
    DEFAULT_CSS = """
    HelpScreen { align: center middle; }
    HelpScreen > Markdown { width: 80; height: auto; border: thick $primary; background: $surface; }
    """

    def compose(self) -> ComposeResult:
        yield Markdown(HELP)
