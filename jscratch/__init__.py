"""jscratch: scratch-based reflection art in JAX.

Stages (data flows one way): ``ndf`` (per-pair scratch NDF) <- ``bvh`` (pixel/scratch binning)
<- ``render`` (multi-view shading) <- ``loss`` <- ``design`` (optimisation); ``scene`` holds the
board, scratches and views every stage shares; ``fabricate`` reads a saved design and drives a
GRBL carver. docs/architecture.md lists each module and what it may import; docs/api.md the
public names by stage; docs/model.md the model.

The public API is re-exported here; the submodules stay importable (``jscratch.render``, ...).
"""

from jscratch.errors import (
    CarveError as CarveError,
    DesignFileError as DesignFileError,
    InputError as InputError,
    JscratchError as JscratchError,
    NonFiniteError as NonFiniteError,
)
from jscratch.designfile import (
    Design as Design,
    DesignError as DesignError,
    load_design as load_design,
    save_design as save_design,
    write_svg as write_svg,
)
from jscratch.ndf import pair_integral as pair_integral
from jscratch.scene import (
    Board as Board,
    Scratches as Scratches,
    Views as Views,
    flat_highlight as flat_highlight,
    views_on_circle as views_on_circle,
)
from jscratch.shading import (
    display as display,
    half_vectors as half_vectors,
    pixel_centres as pixel_centres,
    pixel_footprints as pixel_footprints,
    shade as shade,
)
from jscratch.bvh import (
    PairLists as PairLists,
    Pairs as Pairs,
    bin_pairs as bin_pairs,
    cull_pairs as cull_pairs,
)
from jscratch.render import (
    render_pairs as render_pairs,
    render_reference as render_reference,
)
from jscratch.contributions import scratch_contributions as scratch_contributions
from jscratch.loss import LossConfig as LossConfig, make_loss as make_loss
from jscratch.design import (
    DesignConfig as DesignConfig,
    DesignResult as DesignResult,
    SceneConfig as SceneConfig,
    load_result as load_result,
    save_result as save_result,
)

__version__ = "0.1.0"
