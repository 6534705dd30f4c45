"""``jaxtalk serve``: a WebSocket server that animates live speech (an application layer, like commands/).

* :mod:`jaxtalk.serve.protocol`: the messages (docs/serve.md), their validation and error codes;
* :mod:`jaxtalk.serve.outputs`: what frames are sent as (``params``, ``morph``, ``arkit``), one converter
  per output with a per-client state;
* :mod:`jaxtalk.serve.server`: the asyncio server, :func:`start_server` to run one on a thread.
"""

from jaxtalk.serve.outputs import OUTPUTS, MorphOutput, Output, OutputUnavailable, ParamsOutput
from jaxtalk.serve.protocol import ERROR_CODES, FORMATS, PROTOCOL, ProtocolError
from jaxtalk.serve.server import LiveServer, RunningServer, ServeOptions, start_server

__all__ = ["ERROR_CODES", "FORMATS", "OUTPUTS", "PROTOCOL", "LiveServer", "MorphOutput", "Output", "OutputUnavailable",
           "ParamsOutput", "ProtocolError", "RunningServer", "ServeOptions", "start_server"]
