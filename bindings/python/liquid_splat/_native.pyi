"""The compiled extension module (Rust, PyO3). Use the functions of ``liquid_splat``."""

from typing import Dict, List, Optional, Tuple, Union

import numpy as np

__version__: str
STAGES: List[str]
RECOMMENDED_TOLERANCES: Dict[str, str]

# (dicts: other mappings are refused at run time.)
_Meta = Dict[str, Union[str, bool, int, float]]
_Tensors = Dict[str, np.ndarray]

def run_case(
    tensors: Dict[str, np.ndarray], metadata: _Meta, threads: Optional[int] = None
) -> Tuple[_Tensors, Dict[str, str]]: ...
def load(path: str) -> Tuple[_Tensors, Dict[str, str]]: ...
def save(path: str, tensors: Dict[str, np.ndarray], metadata: Optional[_Meta] = None) -> None: ...
def compare(
    expected: Union[Dict[str, np.ndarray], str],
    actual: Union[Dict[str, np.ndarray], str],
    tolerances_json: Optional[str] = None,
    tolerances_path: Optional[str] = None,
    atol: Optional[float] = None,
    rtol: Optional[float] = None,
    max_mismatch_fraction: Optional[float] = None,
    equal_nan: Optional[bool] = None,
) -> Tuple[bool, str, str]: ...
def field_counts(metadata: _Meta) -> Dict[str, int]: ...
def field_init(metadata: _Meta, seed: int = 0, dtype: str = "float32") -> _Tensors: ...
def cli(args: List[str]) -> int: ...
