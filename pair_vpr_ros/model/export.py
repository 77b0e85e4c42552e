"""The network as fixed-shape graphs for an inference runtime, exported from our modules.

- `EncoderGraph`: one image [1,3,S,S] -> (dense [1,N,D], descriptor [1,desc_dim]);
- `QueryGraph`: a query's dense tokens [N,D] -> what the fast re-rank computes once per query
  (`PairClassifier.query_side`): its stream after block 0's self-attention and its keys/values
  in every block, stacked;
- `ChunkGraph`: that, plus k candidates [k,N,D] -> bidirectional scores [k]
  (`PairClassifier.score_chunk`: class-token-only last block, query keys/values shared);
- `QueryFirstGraph` / `CandidateFirstGraph`: one direction's logits [k], logit(q,c) from the
  query's stream / logit(c,q) from its keys and values (`PairClassifier.chunk_logits`: the
  re-rank cascade's graphs "chunk_query" and "chunk_candidate").

The graphs run the same module code as `PairVPR.encode` / `pair_scores`; only the encoder's
position table, an antialiased bicubic resize that runtimes cannot convert, is computed once here
(for a fixed input size it is a constant). `export_graphs` runs `torch.export` on each.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import torch
from torch import Tensor, nn
from torch.export import ExportedProgram

from pair_vpr_ros.model.network import PairVPR


class EncoderGraph(nn.Module):
    def __init__(self, model: PairVPR) -> None:
        super().__init__()
        self.model = model
        grid = model.config.grid
        with torch.no_grad():
            pos = model.encoder.model.patch_position(grid, grid).detach().clone()
        self.register_buffer("pos", pos)

    def forward(self, images: Tensor) -> tuple[Tensor, Tensor]:
        """images [B,3,S,S] -> dense [B,N,D], L2-normalised descriptors [B,desc_dim]."""
        return self.model.encode(images, pos=self.pos)


class QueryGraph(nn.Module):
    def __init__(self, model: PairVPR) -> None:
        super().__init__()
        self.model = model

    def forward(self, query: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """query [N,D] -> x_query [1,1+N,C], keys and values [L,1,H,N,d] (L decoder blocks)."""
        x_query, memory = self.model.query_side(query)
        keys, values = zip(*memory, strict=True)
        return x_query, torch.stack(keys), torch.stack(values)


class ChunkGraph(nn.Module):
    def __init__(self, model: PairVPR) -> None:
        super().__init__()
        self.model = model

    def forward(self, x_query: Tensor, keys: Tensor, values: Tensor, cands: Tensor) -> Tensor:
        """`QueryGraph`'s outputs and candidates [k,N,D] -> scores [k]."""
        memory = list(zip(keys.unbind(0), values.unbind(0), strict=True))
        return self.model.score_chunk(x_query, memory, cands)


class QueryFirstGraph(nn.Module):
    def __init__(self, model: PairVPR) -> None:
        super().__init__()
        self.model = model

    def forward(self, x_query: Tensor, cands: Tensor) -> Tensor:
        """`QueryGraph`'s stream and candidates [k,N,D] -> logit(q,c) [k]."""
        return self.model.chunk_logits(x_query, [], cands, "query")


class CandidateFirstGraph(nn.Module):
    def __init__(self, model: PairVPR) -> None:
        super().__init__()
        self.model = model

    def forward(self, keys: Tensor, values: Tensor, cands: Tensor) -> Tensor:
        """`QueryGraph`'s keys/values and candidates [k,N,D] -> logit(c,q) [k]."""
        memory = list(zip(keys.unbind(0), values.unbind(0), strict=True))
        return self.model.chunk_logits(keys.new_zeros(0), memory, cands, "candidate")


# The one-direction chunk graphs: which image goes first, which `QueryGraph` outputs they take.
# They take one candidate a call: the cascade steps a candidate at a time, and ViT-B int8 ran
# 115 / 113 / 111 ms a pass at 1 / 2 / 4 candidates (query first; docs/performance.md), so
# larger chunks would mostly pad.
ONE_WAY = {"chunk_query": ("query", (0,)), "chunk_candidate": ("candidate", (1, 2))}
ONE_WAY_CHUNK = 1


@dataclass(frozen=True)
class Graphs:
    """The exported programs and an example input of each (the shapes they are fixed to)."""

    encoder: ExportedProgram
    query: ExportedProgram
    chunk: ExportedProgram
    chunk_size: int
    chunk_query: ExportedProgram | None = None
    chunk_candidate: ExportedProgram | None = None


def example_inputs(model: PairVPR, chunk: int) -> dict[str, tuple[Tensor, ...]]:
    """Zero inputs of each graph's fixed shape (what export traces with)."""
    cfg = model.config
    n, d = cfg.num_patches, cfg.embed_dim
    with torch.no_grad():
        x_query, keys, values = QueryGraph(model)(torch.zeros(n, d))
    return {
        "encoder": (torch.zeros(1, 3, cfg.image_size, cfg.image_size),),
        "query": (torch.zeros(n, d),),
        "chunk": (x_query, keys, values, torch.zeros(chunk, n, d)),
        "chunk_query": (x_query, torch.zeros(ONE_WAY_CHUNK, n, d)),
        "chunk_candidate": (keys, values, torch.zeros(ONE_WAY_CHUNK, n, d)),
    }


def export_graphs(model: PairVPR, chunk: int = 2, one_way: bool = True) -> Graphs:
    """`model` -> its graphs (fp32, CPU), candidates fixed at `chunk` per call; `one_way`: also
    the two one-direction chunk graphs (`ONE_WAY_CHUNK` candidates per call)."""
    model = copy.deepcopy(model).float().cpu().eval()
    inputs = example_inputs(model, chunk)
    graphs = [("encoder", EncoderGraph(model)), ("query", QueryGraph(model))]
    graphs.append(("chunk", ChunkGraph(model)))
    if one_way:
        graphs += [("chunk_query", QueryFirstGraph(model))]
        graphs += [("chunk_candidate", CandidateFirstGraph(model))]
    with torch.no_grad():
        programs = {name: torch.export.export(graph, inputs[name]) for name, graph in graphs}
    return Graphs(chunk_size=chunk, **programs)
